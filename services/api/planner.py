"""Which queued runs start now, on which services, in which groups: one pass over the queue.

Pure over the store's queued rows (oldest first) and the services' infos; the scheduler
claims each start in the store, starts it on the bus, and tells the pass which it
took, so later runs of the pass see those services busy (a start it could not claim,
stopped meanwhile, leaves them free). A run that finds no free services gets a
`waiting: ...` reason, and runs needing as many actors are not tried again in the pass.
With `group_size` > 1 the runs of one experiment that can share a group
(`shared.groups.group_error`: lockstep, one actor, the same config but for the
per-run fields) start together on one assignment naming them (`Assignment.group`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import Any

from shared.config import ConfigError, TrainConfig, make_config
from shared.groups import group_error, group_key
from shared.net.control import NoFreeServices, assign_services
from shared.net.messages import Assignment

Member = tuple[dict[str, Any], TrainConfig]  # a queued run's row and its config


@dataclass(frozen=True)
class Start:
    """Runs to start on one assignment: one run, or a group led by its first."""

    members: list[Member]
    assign: Assignment

    @property
    def ids(self) -> list[str]:
        return [m["id"] for m, _ in self.members]

    def attempt_rows(self) -> list[dict[str, Any]]:
        """The members' rows as the store has them once claimed: a new attempt on this
        assignment (its map, as the store holds it), with no services' states or stats yet."""
        assign = self.assign.to_wire()
        return [{**m, "assign": assign, "services": {}, "live": {}} for m, _ in self.members]


@dataclass(frozen=True)
class Invalid:
    """A queued run whose stored config this API refuses (stored by an older one)."""

    run: str
    reason: str


def group_of(
    run: dict[str, Any],
    config: TrainConfig,
    queued: list[dict[str, Any]],
    taken: Iterable[str],
    group_size: int,
) -> list[Member]:
    """`run` and the queued runs of its experiment that can share its group (in queue
    order, at most `group_size`, none of `taken`); just `run` when it cannot lead one."""
    members = [(run, config)]
    if group_size < 2 or group_error([config], run["actors"]) is not None:
        return members
    key = group_key(config)
    taken = set(taken)
    for other in queued:
        if len(members) >= group_size:
            break
        if other["id"] == run["id"] or other["id"] in taken:
            continue
        if other["experiment_id"] != run["experiment_id"] or other["actors"] != 1:
            continue
        try:
            other_config = make_config(other["config"])
        except ConfigError:
            continue  # refused when its own turn comes
        if group_key(other_config) == key and not group_error([other_config], 1):
            members.append((other, other_config))
    return members


class QueuePass:
    """One pass over the queue: `proposals` yields what to start (or refuse), `took`
    records a start that was claimed, `waiting` is what the runs left wait for."""

    def __init__(
        self,
        queued: list[dict[str, Any]],
        infos: list[dict[str, Any]],
        reserved: set[str],
        group_size: int = 1,
    ) -> None:
        self.queued = queued
        self.group_size = group_size
        # Services of runs started earlier whose own info does not say so yet are busy.
        self.infos = [dict(i) for i in infos]
        for info in self.infos:
            if info["role"] != "counter" and info["id"] in reserved:
                info["run"] = info.get("run") or "(reserved)"
        self.waiting: dict[str, str] = {}  # run id -> reason (only where it changes)
        self._refused: dict[int, str] = {}  # actors needed -> why not (for this pass)
        self._started: set[str] = set()  # runs started this pass (a group's members)

    def proposals(self) -> Iterator[Start | Invalid]:
        for run in self.queued:
            if run["id"] in self._started:
                continue
            why = self._refused.get(run["actors"])
            if why is None:
                try:
                    assign = assign_services(self.infos, run["actors"])
                except NoFreeServices as err:
                    why = self._refused[run["actors"]] = f"waiting: {err}"
            if why is not None:
                if run["reason"] != why:
                    self.waiting[run["id"]] = why
                continue
            try:
                config = make_config(run["config"])
            except ConfigError as err:
                yield Invalid(run["id"], f"invalid config: {err}")
                continue
            members = group_of(run, config, self.queued, self._started, self.group_size)
            if len(members) > 1:
                assign = dataclasses.replace(assign, group=tuple(m["id"] for m, _ in members))
            yield Start(members, assign)

    def took(self, start: Start) -> None:
        """`start` was claimed: its runs are not started again, its services are busy."""
        self._started.update(start.ids)
        taken = start.assign.held()
        for info in self.infos:
            if info["id"] in taken and info["role"] != "counter":
                info["run"] = start.ids[0]
