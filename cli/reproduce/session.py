"""`macb reproduce` through the API: follow the figure's experiment on a cluster that
answers at --api, or on the local cluster this command starts, and write its page.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import urlparse

from cli.reproduce.defs import FigureDef
from shared.persist.files import default_data_dir

if TYPE_CHECKING:
    from services.api.client import ApiClient

RETRYABLE = ("failed", "stopped")


def answers_at(api: ApiClient) -> bool:
    import httpx

    from services.api.client import ApiError

    try:
        api.health()
        return True
    except (httpx.HTTPError, ApiError):
        return False


def with_local_cluster(
    args: argparse.Namespace, url: str, fig: FigureDef, body: dict[str, Any], out: Path
) -> int:
    """No API answers at `url`: bring the local cluster up with its API there, run the
    figure, bring it down. A signal stops the experiment first (so every service marks
    its runs stopped, and the next run of this command retries them), then the cluster."""
    from cli.cluster import ClusterDidNotStart, local_cluster

    where = urlparse(url)
    if where.hostname not in ("127.0.0.1", "localhost") or not where.port:
        print(
            f"macb reproduce: no API answers at {url}, and a local cluster's API listens on "
            "127.0.0.1:PORT (give --api http://127.0.0.1:PORT, or start the API)",
            file=sys.stderr,
        )
        return 1
    print(f"no API answers at {url}: starting the local cluster", file=sys.stderr)
    data_dir = Path(args.data_dir or default_data_dir())
    try:
        with local_cluster(
            1,
            args.endpoint,
            data_dir,
            f"127.0.0.1:{where.port}",
            echo=not args.quiet_services,
            slots=args.slots,
            group_size=args.group_size or cluster_group_size(body, args.slots),
        ) as up:
            if up.stop.is_set() or up.api is None:
                return 1
            session = Session(up.api, fig, body, args.profile, out, args.quiet)
            code = up.run(session.run)
            if up.stop.is_set():
                return session.interrupted()
            return code
    except ClusterDidNotStart as err:
        return err.code


def cluster_group_size(body: dict[str, Any], slots: int) -> int:
    """The figure's runs split evenly over the local cluster's slots: one group each."""
    runs = len(body.get("arms") or [None]) * len(body.get("seeds") or [None])
    return max(1, -(-runs // slots))


class Session:
    """One `macb reproduce`: find or create the experiment, queue again what did not
    complete, follow it, and write the report."""

    def __init__(
        self,
        api: ApiClient,
        fig: FigureDef,
        body: dict[str, Any],
        profile: str,
        out: Path,
        quiet: bool,
    ) -> None:
        self.api, self.fig, self.body, self.profile = api, fig, body, profile
        self.out, self.quiet = out, quiet
        self.exp_id: str | None = None
        self.cancelled = False  # interrupted: stop following, write nothing

    def run(self) -> int:
        """Follow the experiment to its end and write the report; the exit code."""
        import httpx

        from services.api.client import ApiError

        try:
            return self._run()
        except Exception as err:
            if self.cancelled:  # interrupted: the main thread has closed the client
                return 1
            if isinstance(err, ApiError | httpx.HTTPError | TimeoutError):
                print(f"macb reproduce: the API at {self.api.url}: {err}", file=sys.stderr)
                return 1
            raise

    def _run(self) -> int:
        from services.api.client import follow_experiment

        exp, inherited = self._find_or_create()
        retried: set[str] = set()
        while not self.cancelled:
            exp = follow_experiment(self.api, exp["id"], quiet=self.quiet)
            # A run found running when this command resumed, that has failed since, was
            # left by an earlier command that did not end cleanly (the API fails such a
            # run once it sees no service serve it): queue it again, once.
            again = [
                r["id"]
                for r in exp["runs"]
                if r["status"] == "failed" and r["id"] in inherited - retried
            ]
            if not again or self.cancelled:
                break
            print(
                f"{len(again)} run(s) left running by an earlier command failed: "
                "queueing them again",
                file=sys.stderr,
            )
            self.api.retry_experiment(exp["id"], again)
            retried.update(again)
        if self.cancelled:
            return 1
        return self._report(exp)

    def _find_or_create(self) -> tuple[dict[str, Any], set[str]]:
        """The experiment (found by name and its runs that did not complete queued again,
        or created) and the ids of the runs it found running."""
        name = self.body["name"]
        found = self._find(name)
        if found is None:
            exp = self.api.create_experiment(self.body)
            self.exp_id = exp["id"]
            print(
                f"experiment {exp['id']} ({name}): {len(exp['runs'])} run(s) queued; follow "
                f"it at {self.api.url}/  (Ctrl-C stops it; the same command resumes it)",
                file=sys.stderr,
            )
            return exp, set()
        self.exp_id = found["id"]
        counts = ", ".join(f"{v} {k}" for k, v in found["counts"].items())
        print(f"resuming experiment {found['id']} ({name}): {counts}", file=sys.stderr)
        running = {r["id"] for r in found["runs"] if r["status"] == "running"}
        if any(r["status"] in RETRYABLE for r in found["runs"]):
            done = self.api.retry_experiment(found["id"])
            print(f"experiment {found['id']}: {done['detail']}", file=sys.stderr)
            return done["experiment"], running
        return found, running

    def _find(self, name: str) -> dict[str, Any] | None:
        """The newest experiment with this name in the store, or None."""
        offset = 0
        while True:
            page = self.api.experiments(limit=200, offset=offset)
            for exp in page["experiments"]:  # newest first
                if exp["name"] == name:
                    return exp
            offset += len(page["experiments"])
            if not page["experiments"] or offset >= page["total"]:
                return None

    def _report(self, exp: dict[str, Any]) -> int:
        from cli.reproduce.analysis import analyse, claim_verdicts, columns
        from cli.reproduce.render import write_report

        points = {r["id"]: columns(self.api.all_points(r["id"])) for r in exp["runs"]}
        analysis = analyse(self.fig, exp, points)
        paths = write_report(analysis, points, self.profile, self.out)
        verdicts = [v for *_, v in claim_verdicts(analysis)]
        tally = ", ".join(f"{verdicts.count(v)} {v}" for v in dict.fromkeys(verdicts))
        print(
            f"experiment {exp['id']} {exp['status']}; claims: {tally}; wrote "
            + ", ".join(str(p) for p in paths),
            file=sys.stderr,
        )
        return 0 if exp["status"] == "completed" else 1

    def interrupted(self) -> int:
        """Ctrl-C / SIGTERM: stop the experiment (its runs end `stopped`, which the same
        command retries) and give the services a moment to hear it."""
        self.cancelled = True
        if self.exp_id is None:
            return 1
        try:
            self.api.stop_experiment(self.exp_id)
            time.sleep(1.0)  # the scheduler sends the stops within a tick (0.2 s)
        except Exception as err:  # the API may be going down too
            print(f"could not stop experiment {self.exp_id}: {err}", file=sys.stderr)
        print(
            f"experiment {self.exp_id} stopped; run the same command again to resume it",
            file=sys.stderr,
        )
        return 1
