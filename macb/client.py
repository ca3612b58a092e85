"""Experiments in the API from Python: start, follow, stop, and an experiment as the same
DataFrame `load_runs` gives for a runs folder (so `macb.summary` reads either).

A thin layer over services/api/client.py's ApiClient, the client `macb run`, `ls`, `stop`
and `plot` use, so the URL and token rules are the command line's: the URL given, else
MACB_API_URL, else http://127.0.0.1:8000; the token given, else MACB_API_TOKEN, sent as
`Authorization: Bearer`. A refusal (a wrong token: 401, an unknown id: 404, a bad body:
422) raises ApiError with the status and the API's reason.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import pandas as pd

from macb.runs import joined, run_frame
from services.api.client import ApiClient, ApiError

ENDED = ("completed", "stopped", "failed")

__all__ = ["ApiError", "Client"]


class Client:
    """The API at `url` (see the module's docstring for the defaults)."""

    def __init__(self, url: str | None = None, token: str | None = None, timeout: float = 30.0):
        self.api = ApiClient(url, token, timeout)

    @property
    def url(self) -> str:
        return self.api.url

    def close(self) -> None:
        self.api.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self, body: dict[str, Any]) -> dict[str, Any]:
        """Create an experiment (POST /experiments: config keys, `seeds`, `grid`, `arms`;
        docs/api.md); the experiment with its runs. Its id is `["id"]`."""
        return self.api.create_experiment(body)

    def experiment(self, experiment_id: str) -> dict[str, Any]:
        return self.api.experiment(experiment_id)

    def stop(self, experiment_id: str) -> dict[str, Any]:
        """Stop the experiment's queued and running runs (idempotent: the answer says
        whether anything changed)."""
        return self.api.stop_experiment(experiment_id)

    def experiment_frame(self, experiment_id: str) -> pd.DataFrame:
        """Every stored point of the experiment, one row each: run (its id), arm, seed,
        the metrics, then its config as `config.*` columns, as `load_runs` gives them."""
        exp = self.api.experiment(experiment_id)
        frames = [
            run_frame(
                r["id"], r["arm"], r["seed"], _rows(self.api.all_points(r["id"])), r["config"]
            )
            for r in exp["runs"]
        ]
        return joined(frames)  # an experiment has at least one run

    def follow(self, experiment_id: str, poll_s: float = 1.0) -> Iterator[dict[str, Any]]:
        """Each new point of the experiment's runs as it is stored (a dict with `run`,
        `arm`, `seed` and `attempt` besides the metric row), polled every `poll_s` s,
        until every run has ended and its last point was given. Stop early by leaving
        the loop. A run retried meanwhile gives its new attempt's points after the old
        ones, episodes again from its start, with the higher `attempt`: the earlier
        attempt's rows are superseded (the store keeps only the latest attempt's)."""
        since: dict[str, int] = {}
        while True:
            exp = self.api.experiment(experiment_id)
            ended = all(r["status"] in ENDED for r in exp["runs"])
            for r in exp["runs"]:
                while True:  # every page stored so far
                    got = self.api.metrics(r["id"], since.get(r["id"], 0))
                    head = {"run": r["id"], "arm": r["arm"], "seed": r["seed"]}
                    for p in _rows(got["points"]):
                        yield {**head, "attempt": got.get("attempt"), **p}
                    if got["points"]:
                        since[r["id"]] = got["next_since"]
                    if not got["more"]:
                        break
            if ended:  # the status was read before the points: none can come after
                return
            time.sleep(poll_s)


def _rows(points: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The API's points as metric rows (without the store's `seq`)."""
    return [{k: v for k, v in p.items() if k != "seq"} for p in points]
