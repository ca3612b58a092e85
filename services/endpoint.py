"""A service's side of the bus: subscriptions whose callbacks only enqueue and
publishers (those of a run end with it, so a service never receives the traffic of
runs others serve, and a long-lived one holds no declarations of runs long over), and
its statuses and metric rows out."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from shared.net import bus as keys
from shared.net.bus import Bus, Publisher
from shared.net.messages import Metrics, Resumed, Status
from shared.net.wire import encode


class Endpoint:
    """`put` enqueues (tag, key, payload) for the service's thread."""

    def __init__(self, bus: Bus, put: Callable[[Any], None], service_id: str, role: str) -> None:
        self.bus, self.put, self.id, self.role = bus, put, service_id, role
        self.run_subs: dict[str, list] = {}  # run -> its subscriptions and publishers

    def listen(self, key_expr: str, tag: str, run: str | None = None) -> None:
        """Subscribe; the callback only enqueues (tag, key, payload). With `run`, the
        subscription belongs to that run and ends when the run is freed."""
        put = self.put
        self.subscribe(key_expr, lambda key, payload: put((tag, key, payload)), run)

    def subscribe(self, key_expr: str, callback: Callable, run: str | None = None) -> None:
        handle = self.bus.subscribe(key_expr, callback)
        if run is not None:
            self.run_subs.setdefault(run, []).append(handle)

    def publisher(self, key: str, run: str) -> Publisher:
        """A publisher that belongs to `run` (or to what a group's subscriptions are held
        under): undeclared when the run is freed."""
        pub = self.bus.publisher(key)
        self.run_subs.setdefault(run, []).append(pub)
        return pub

    def drop_run(self, run: str) -> None:
        """The run's subscriptions and publishers end."""
        for handle in self.run_subs.pop(run, []):
            self.bus.undeclare(handle)

    def status(
        self,
        run: str,
        state: str,
        *,
        reason: str | None = None,
        final_seq: int | None = None,
        points: int | None = None,
        resumed: Resumed | None = None,
        attempt: int | None = None,
        **detail: Any,
    ) -> None:
        """The service's `Status` in the run (its `attempt`): the fields a reader acts
        on, the rest (where it is, its stats) as its detail."""
        msg = Status(
            run,
            service=self.id,
            state=state,
            detail=detail,
            reason=reason,
            final_seq=final_seq,
            points=points,
            resumed=resumed,
            attempt=attempt,
        )
        self.bus.put(keys.k_status(run, self.id), encode(msg))

    def metrics(
        self,
        run: str,
        data: dict[str, Any],
        source: str | None = None,
        attempt: int | None = None,
    ) -> None:
        source = source or f"{self.role}/{self.id}"
        msg = Metrics(run, source=source, data=data, attempt=attempt)
        self.bus.put(keys.k_metrics(run, source), encode(msg))
