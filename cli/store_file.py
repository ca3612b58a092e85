"""An API store file read by the command line (`macb export --db`, `macb plot --db`): only
read, never migrated or made, and refused naming it when it is no store."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

STORE_TABLES = {"schema_version", "experiments", "runs", "metrics"}


class NotAStore(Exception):
    """The --db file is not an API store (named, with the reason)."""


def store_file_error(db: str) -> str | None:
    """Why `db` is no store file to read (missing, a folder), or None: asked before
    anything is read or written, as a Store would make a missing file."""
    path = Path(db)
    if path.is_dir():
        return f"{db}: a folder, not a store file (the API's, DATA_DIR/api.sqlite3)"
    if not path.is_file():
        return f"no store file {db}"
    return None


@contextlib.contextmanager
def store_copy(db: str) -> Iterator[Any]:
    """A store file, only read: opening a store migrates it to this version's schema (and
    makes any file one), so a consistent copy is opened instead, and an older API can
    still read its own file after. NotAStore, naming the file, if it is not an API store
    this version reads."""
    import sqlite3
    import tempfile

    from services.api.db import StoreError
    from services.api.store import Store

    with tempfile.TemporaryDirectory(prefix="macb-store-") as tmp:
        copy = Path(tmp) / "store.sqlite3"
        try:
            _copy(Path(db), copy)
            store = Store(copy)
        except OSError as err:  # (gone or unreadable since it was checked)
            raise NotAStore(f"{db}: cannot be read ({err.strerror or err})") from None
        except (sqlite3.Error, StoreError) as err:
            raise NotAStore(f"{db}: not a store this version reads ({err})") from None
        try:
            yield store
        finally:
            store.close()


def _copy(db: Path, copy: Path) -> None:
    """`db` copied to `copy`. With a `-wal` beside it (a running API's, or one that ended
    without its checkpoint) through SQLite's backup, which reads the log too; without,
    its bytes: SQLite opening a store of journal mode WAL, even read-only, would leave a
    `-wal` and a `-shm` beside it. Bytes read while the file changed (an API started
    meanwhile: a `-wal` beside it after, another size or time) or that do not check are
    read again through SQLite."""
    import shutil
    import sqlite3

    wal = Path(f"{db}-wal")
    if not wal.exists():
        before = _stamp(db)
        shutil.copyfile(db, copy)
        if not wal.exists() and _stamp(db) == before:
            with contextlib.suppress(sqlite3.DatabaseError):
                if _checked(db, copy):
                    return
        copy.unlink()
    src = sqlite3.connect(f"{db.resolve().as_uri()}?mode=ro", uri=True)
    try:
        with sqlite3.connect(copy) as dst:
            src.backup(dst)
        dst.close()
    finally:
        src.close()
    if not _checked(db, copy):
        raise sqlite3.DatabaseError("the file does not pass SQLite's quick_check")


def _stamp(path: Path) -> tuple[int, int]:
    st = path.stat()
    return st.st_size, st.st_mtime_ns


def _checked(db: Path, copy: Path) -> bool:
    """Whether `db`'s copy passes SQLite's quick check; NotAStore if it is a database
    but not a store."""
    import sqlite3

    con = sqlite3.connect(copy)
    try:
        ok = con.execute("PRAGMA quick_check").fetchone()[0] == "ok"
        tables = {r[0] for r in con.execute("SELECT name FROM sqlite_master")}
    finally:
        con.close()
    if ok and not tables >= STORE_TABLES:
        raise NotAStore(f"{db}: not a macb API store (no experiments, runs, metrics)")
    return ok
