"""The names of an experiment's arms: what a run carries, curves group by and legends show.

One place for the rule, because the schema names new runs with it and the store names
the runs of files written before runs carried a name (schema 1) with it: an arm's name
is its own; a grid point's is `key=value,...` in config-field order; an arm crossed
with a grid point is both; a run with neither is named after its algorithm and bonus.
"""

from __future__ import annotations

import json
from typing import Any


def format_value(value: Any) -> str:
    """A config value as it reads in a name: floats round-trip (`repr`, so two points
    never share a name), booleans as YAML writes them, lists as JSON."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, list | tuple):
        return json.dumps(list(value))
    return str(value)


def point_name(point: dict[str, Any]) -> str:
    """`beta=0.8,k=64`: a grid point's name (its keys in the order given)."""
    return ",".join(f"{key}={format_value(value)}" for key, value in point.items())


def base_name(config: dict[str, Any]) -> str:
    """The single arm of an experiment without arms or grid: `cen-maddpg + cen-macb`."""
    return f"{config.get('algo')} + {config.get('explore')}"


def run_name(arm: str | None, grid_point: dict[str, Any], config: dict[str, Any]) -> str:
    """The name a run carries: arm, grid point, both (`cen-macb beta=0.2`), or neither."""
    parts = [p for p in (arm, point_name(grid_point)) if p]
    return " ".join(parts) if parts else base_name(config)
