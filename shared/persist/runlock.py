"""One writer per run folder: an exclusive lock on `<folder>/.lock` for as long as a
process trains the run in it.

Two processes training one run folder interleave their writes: both truncate and append
metrics.jsonl (NUL holes where one's offset is past the other's truncation), both append
to the replay log and write cuts, and a resume then reads a mixture. So whoever trains a
run (`macb train --out`, a `--local` group, a Slurm task: all through
`cli.trainer.train_group`) holds its folder's lock, and a second one is refused, naming
the holder's PID, before it touches anything.

`fcntl.flock` rather than a PID file: the kernel drops the lock when its holder ends in
any way (SIGKILL, a crash, a node reboot), so a lock is never stale and nothing needs
cleaning up; the PID written in the file is only there to name the holder. On NFS, Linux
emulates flock with byte-range locks the server sees, so tasks on several nodes exclude
each other too (Lustre needs its `flock` mount option).
"""

from __future__ import annotations

import contextlib
import fcntl
import os
from collections.abc import Iterator, Sequence
from pathlib import Path

FILE = ".lock"


class RunLocked(RuntimeError):
    """Another process trains this run folder: refused, naming it and its holder."""

    def __init__(self, folder: Path, holder: int | None) -> None:
        self.folder, self.holder = folder, holder
        who = f"PID {holder}" if holder else "another process (PID not written yet)"
        super().__init__(
            f"{folder}: {who} is training this run (it holds {folder / FILE}); "
            "nothing was done: wait for it or end it first"
        )


def holder(folder: Path) -> int | None:
    """The PID written in `folder`'s lock file, or None (no file, empty, unreadable)."""
    try:
        text = (folder / FILE).read_text().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


def is_locked(folder: Path) -> int | None:
    """Whether some process holds `folder`'s lock now: its PID (0 when it wrote none
    yet), or None. Creates nothing: a folder without a lock file is free."""
    try:
        fd = os.open(folder / FILE, os.O_RDONLY)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return holder(folder) or 0
    finally:
        os.close(fd)  # closing drops the shared lock taken to look
    return None


@contextlib.contextmanager
def hold(folders: Sequence[Path]) -> Iterator[None]:
    """Hold every folder's lock (each folder created if missing) for the block, or raise
    `RunLocked` for the first one another process holds, having taken none of them and
    written nothing (the file's PID is written only once its lock is ours)."""
    fds: list[int] = []
    try:
        for folder in folders:
            folder.mkdir(parents=True, exist_ok=True)
            fd = os.open(folder / FILE, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                raise RunLocked(folder, holder(folder)) from None
            fds.append(fd)
        for fd in fds:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        for fd in fds:
            os.close(fd)
