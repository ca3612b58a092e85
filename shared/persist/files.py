"""Small JSON files beside a run's data: read without failing, replaced atomically; and
where that data goes by default."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any


def write_json(path: Path, data: Any) -> None:
    """Replace `path` with `data` as JSON: a crash leaves the old file or the new one."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=1, sort_keys=True))
    os.replace(tmp, path)


def read_json(path: Path) -> Any:
    """The file's JSON, or None when it is missing or unreadable."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


DATA_DIR_RULE = "$XDG_STATE_HOME/macb, else ~/.local/state/macb"


def default_data_dir() -> Path:
    """Where the services, the local cluster and the API keep their data unless given a
    --data-dir: per user and outside any checkout (`DATA_DIR_RULE`; a relative
    XDG_STATE_HOME is ignored, as the XDG spec says)."""
    state = os.environ.get("XDG_STATE_HOME", "")
    base = Path(state) if os.path.isabs(state) else Path.home() / ".local" / "state"
    return base / "macb"


def data_dir_help(what: str) -> str:
    """A --data-dir flag's help: what goes there and where that is by default."""
    return f"{what} (default: {DATA_DIR_RULE}; here {default_data_dir()})"
