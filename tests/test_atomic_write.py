"""`atomic_write` with a previous file kept: a kill at any step leaves a whole file at
the path others read (the learner's checkpoint.pt is read by a restart and by tests that
tear it), and the previous one beside it once the new one is written."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from shared.persist import files
from shared.persist.files import atomic_write


class Killed(Exception):
    """Stands for SIGKILL at one step: nothing after it runs."""


def _write(body: bytes):
    return lambda f: f.write(body)


def test_the_new_file_replaces_the_old_which_is_kept_as_previous(tmp_path: Path):
    path, prev = tmp_path / "checkpoint.pt", tmp_path / "checkpoint.prev.pt"
    atomic_write(path, _write(b"one"), prev)
    assert path.read_bytes() == b"one" and not prev.exists()
    atomic_write(path, _write(b"two"), prev)
    atomic_write(path, _write(b"three"), prev)
    assert path.read_bytes() == b"three" and prev.read_bytes() == b"two"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.prev.pt", "checkpoint.pt"]


@pytest.mark.parametrize("step", ["link", "replace-previous", "replace-path"])
def test_a_kill_at_any_step_leaves_a_whole_file_at_the_path(tmp_path: Path, monkeypatch, step):
    path, prev = tmp_path / "checkpoint.pt", tmp_path / "checkpoint.prev.pt"
    atomic_write(path, _write(b"old"), prev)
    atomic_write(path, _write(b"older-than-new"), prev)  # (prev: b"old")
    real_link, real_replace = os.link, os.replace

    def link(src, dst):
        if step == "link":
            raise Killed
        real_link(src, dst)

    def replace(src, dst):
        if (step == "replace-previous" and Path(dst) == prev) or (
            step == "replace-path" and Path(dst) == path
        ):
            raise Killed
        real_replace(src, dst)

    monkeypatch.setattr(files.os, "link", link)
    monkeypatch.setattr(files.os, "replace", replace)
    with pytest.raises(Killed):
        atomic_write(path, _write(b"new"), prev)
    assert path.read_bytes() == b"older-than-new"  # the path never lacks a whole file
    assert prev.read_bytes() == (b"older-than-new" if step == "replace-path" else b"old")
    monkeypatch.undo()
    atomic_write(path, _write(b"after"), prev)  # the leftovers of the kill are no obstacle
    assert path.read_bytes() == b"after" and prev.read_bytes() == b"older-than-new"


def test_where_hard_links_are_refused_the_previous_file_is_a_copy(tmp_path: Path, monkeypatch):
    path, prev = tmp_path / "checkpoint.pt", tmp_path / "checkpoint.prev.pt"
    atomic_write(path, _write(b"old"), prev)

    def refuse(src, dst):
        raise PermissionError("no hard links here")

    monkeypatch.setattr(files.os, "link", refuse)
    atomic_write(path, _write(b"new"), prev)
    assert path.read_bytes() == b"new" and prev.read_bytes() == b"old"
