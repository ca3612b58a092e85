"""An API store file read by the command line (`macb export --db`, `macb plot --db`): only
read, never migrated or made, and refused naming it when it is no store."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any


class NotAStore(Exception):
    """The --db file is not an API store (named, with the reason)."""


@contextlib.contextmanager
def store_copy(db: str) -> Iterator[Any]:
    """A store file, only read: opening a store migrates it to this version's schema (and
    makes any file one), so a consistent copy (SQLite's backup, a running API's WAL
    included) is opened instead, and an older API can still read its own file after.
    NotAStore, naming the file, if it is not an API store this version reads."""
    import sqlite3
    import tempfile

    from services.api.db import StoreError
    from services.api.store import Store

    with tempfile.TemporaryDirectory(prefix="macb-store-") as tmp:
        copy = Path(tmp) / "store.sqlite3"
        try:
            src = sqlite3.connect(f"{Path(db).resolve().as_uri()}?mode=ro", uri=True)
            try:
                tables = {r[0] for r in src.execute("SELECT name FROM sqlite_master")}
                if not {"schema_version", "experiments", "runs", "metrics"} <= tables:
                    raise NotAStore(f"{db}: not a macb API store (no experiments, runs, metrics)")
                with sqlite3.connect(copy) as dst:
                    src.backup(dst)
                dst.close()
            finally:
                src.close()
            store = Store(copy)
        except (sqlite3.Error, StoreError) as err:
            raise NotAStore(f"{db}: not a store this version reads ({err})") from None
        try:
            yield store
        finally:
            store.close()
