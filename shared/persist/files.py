"""Small JSON files beside a run's data: read without failing, replaced atomically; and
where that data goes by default."""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO


def fsync_dir(path: Path) -> None:
    """A rename inside `path` survives the machine once its directory is fsynced."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write(
    path: Path, write: Callable[[BinaryIO], Any], previous: Path | None = None
) -> None:
    """The one way a file others rely on is replaced: `write` fills a temporary file,
    which is fsynced and renamed over `path`, so a crash leaves the old file or the new
    one, whole. With `previous`, the old file is kept there too: it is hard-linked (a
    copy where links are refused) to `previous` before the new one replaces it, so a
    kill at any point leaves a whole file at `path`, never a moment without one."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        write(f)
        f.flush()
        os.fsync(f.fileno())
    if previous is not None and path.exists():
        keep = previous.with_name(previous.name + ".tmp")
        keep.unlink(missing_ok=True)
        try:
            os.link(path, keep)
        except OSError:  # a filesystem without hard links
            shutil.copyfile(path, keep)
        os.replace(keep, previous)
    os.replace(tmp, path)
    fsync_dir(path.parent)


def write_json(path: Path, data: Any) -> None:
    """Replace `path` with `data` as JSON (`atomic_write`)."""
    body = json.dumps(data, indent=1, sort_keys=True).encode()
    atomic_write(path, lambda f: f.write(body))


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
