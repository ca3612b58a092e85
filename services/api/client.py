"""A small HTTP client of the API (what `macb run`, `ls`, `stop` and `plot` use)."""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from typing import Any

import httpx

from shared.settings import settings

DEFAULT_URL = "http://127.0.0.1:8000"


class ApiError(RuntimeError):
    def __init__(self, status: int, detail: Any) -> None:
        self.status = status
        self.detail = detail
        super().__init__(f"HTTP {status}: {format_detail(detail)}")


def format_detail(detail: Any) -> str:
    if isinstance(detail, list):  # validation errors: field and reason each
        return "; ".join(f"{e.get('field', 'body')}: {e.get('msg')}" for e in detail)
    return str(detail)


class ApiClient:
    def __init__(self, url: str | None = None, token: str | None = None, timeout: float = 30.0):
        env = settings()
        self.url = (url or env.api_url or DEFAULT_URL).rstrip("/")
        token = token or env.api_token
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.http = httpx.Client(base_url=self.url, headers=headers, timeout=timeout)

    def close(self) -> None:
        self.http.close()

    def __enter__(self) -> ApiClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _call(self, method: str, path: str, **kw: Any) -> Any:
        r = self.http.request(method, path, **kw)
        if r.status_code >= 400:
            try:
                detail = r.json().get("detail", r.text)
            except ValueError:
                detail = r.text
            raise ApiError(r.status_code, detail)
        return r.json() if r.headers.get("content-type", "").startswith("application/json") else r

    def health(self) -> dict[str, Any]:
        return self._call("GET", "/health")

    def wait_healthy(self, timeout: float = 30.0, alive: Callable[[], bool] = lambda: True) -> None:
        """Until /health says the API is on the bus (TimeoutError after `timeout`, or once
        `alive()` is false). An answer counts only while `alive()` holds, asked after it:
        an API process that died (its port taken) is not stood in for by whoever else
        answers at the URL."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                if self.health().get("bus") and alive():
                    return
            except (httpx.HTTPError, ApiError):
                pass
            if not alive():
                raise TimeoutError(f"the API at {self.url} did not become ready: a process ended")
            if time.monotonic() > deadline:
                raise TimeoutError(f"the API at {self.url} did not become ready")
            time.sleep(0.2)

    def workers(self) -> dict[str, Any]:
        """GET /workers: every service the API has seen, and whether it answers."""
        return self._call("GET", "/workers")

    def create_experiment(self, body: dict[str, Any]) -> dict[str, Any]:
        return self._call("POST", "/experiments", json=body)

    def experiments(self, limit: int = 100, offset: int = 0) -> dict[str, Any]:
        return self._call("GET", "/experiments", params={"limit": limit, "offset": offset})

    def experiment(self, exp_id: str) -> dict[str, Any]:
        return self._call("GET", f"/experiments/{exp_id}")

    def stop_experiment(self, exp_id: str) -> dict[str, Any]:
        return self._call("POST", f"/experiments/{exp_id}/stop")

    def retry_experiment(self, exp_id: str, runs: list[str] | None = None) -> dict[str, Any]:
        """Queue its failed and stopped runs again (only `runs`, if given)."""
        params = {"run": runs} if runs else None
        return self._call("POST", f"/experiments/{exp_id}/retry", params=params)

    def run(self, run_id: str) -> dict[str, Any]:
        return self._call("GET", f"/runs/{run_id}")

    def stop_run(self, run_id: str) -> dict[str, Any]:
        return self._call("POST", f"/runs/{run_id}/stop")

    def metrics(self, run_id: str, since: int = 0, limit: int | None = None) -> dict[str, Any]:
        params = {"since": since, **({"limit": limit} if limit else {})}
        return self._call("GET", f"/runs/{run_id}/metrics", params=params)

    def all_points(self, run_id: str, page: int = 50_000) -> list[dict[str, Any]]:
        """Every stored point of a run, page by page (a 50,000-episode run has 50,000),
        all of one attempt: a retry between two pages deletes the points read so far,
        so the read starts over from the new attempt's first point."""
        points: list[dict[str, Any]] = []
        since, attempt = 0, None
        while True:
            got = self.metrics(run_id, since, limit=page)
            if attempt is not None and got.get("attempt") != attempt:
                points, since, attempt = [], 0, None  # retried meanwhile: read it again
                continue
            attempt = got.get("attempt")  # (None from an API older than the field)
            points += got["points"]
            if not got["more"] or not got["points"]:
                return points
            since = got["next_since"]

    def metrics_csv(self, run_id: str) -> str:
        return self._call("GET", f"/runs/{run_id}/metrics.csv").text

    def experiment_csv(self, exp_id: str) -> str:
        return self._call("GET", f"/experiments/{exp_id}/metrics.csv").text

    def curves(self, exp_id: str, metrics: list[str]) -> dict[str, Any]:
        return self._call("GET", f"/experiments/{exp_id}/curves", params={"metric": metrics})

    def events(self, run_id: str, since: int = 0) -> Iterator[tuple[str, dict[str, Any]]]:
        """(event, data) from GET /runs/{id}/events until the stream ends."""
        with self.http.stream(
            "GET", f"/runs/{run_id}/events", params={"since": since}, timeout=None
        ) as r:
            if r.status_code >= 400:
                r.read()
                raise ApiError(r.status_code, r.json().get("detail"))
            yield from parse_sse(r.iter_lines())


def parse_sse(lines: Iterator[str]) -> Iterator[tuple[str, dict[str, Any]]]:
    event, data = "message", list[str]()
    for line in lines:
        if not line:
            if data:
                yield event, json.loads("\n".join(data))
            event, data = "message", []
        elif line.startswith(":"):
            continue
        elif line.startswith("event:"):
            event = line[6:].strip()
        elif line.startswith("data:"):
            data.append(line[5:].strip())


def follow_experiment(
    client: ApiClient,
    exp_id: str,
    quiet: bool = False,
    poll_s: float = 1.0,
    patience_s: float = 120.0,
) -> dict[str, Any]:
    """Poll an experiment with a progress bar until every run has ended; the experiment.

    The API going away for a while (a restart) is waited out for `patience_s`.
    """
    from tqdm import tqdm

    exp = client.experiment(exp_id)
    total = sum(r["progress"]["episodes"] for r in exp["runs"])
    bar = tqdm(total=total, unit="ep", disable=quiet, desc=exp["name"][:40])
    lost_since = None
    try:
        while True:
            try:
                exp = client.experiment(exp_id)
                lost_since = None
            except httpx.HTTPError as err:
                lost_since = lost_since or time.monotonic()
                if time.monotonic() - lost_since > patience_s:
                    raise TimeoutError(f"lost the API at {client.url}: {err}") from err
                time.sleep(poll_s)
                continue
            done = sum(
                p["episodes"] if r["status"] == "completed" else p["episode"]
                for r in exp["runs"]
                for p in [r["progress"]]
            )
            bar.update(max(0, done - bar.n))
            counts = exp["counts"]
            successes = [
                r["live"]["eval"]["success_rate"] for r in exp["runs"] if r["live"].get("eval")
            ]
            bar.set_postfix(
                runs=" ".join(f"{v} {k}" for k, v in counts.items()),
                success=f"{sum(successes) / len(successes):.2f}" if successes else "-",
            )
            if exp["status"] not in ("queued", "running"):
                return exp
            time.sleep(poll_s)
    finally:
        bar.close()
