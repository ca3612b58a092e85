"""provenance.json: every start of a run records what it ran on, the learner's precision
as run (not only as asked) among it; a file that is not a record is refused by name."""

from __future__ import annotations

import json
import re
import subprocess

import pytest
import torch

from cli.main import main
from cli.trainer import train
from shared.config import make_config
from shared.core.learners import precision
from shared.persist import provenance
from shared.persist.cuts import CutError
from tests.harness import ROOT, TINY

SMALL = {**TINY, "episodes": 6, "eval_every": 2, "k": 32, "learner_lanes": 1}
ZEN3 = "processor\t: 0\nmodel name\t: AMD EPYC 7B13\nflags\t\t: fpu sse avx2 fma\n"
ZEN4 = "processor\t: 0\nmodel name\t: AMD EPYC 9B14\nflags\t\t: avx2 avx512f avx512_bf16\n"


def test_machine_names_the_cpu_and_its_native_bf16_flags():
    assert provenance.machine(ZEN3)["cpu"] == "AMD EPYC 7B13"
    assert provenance.machine(ZEN3)["bf16_flags"] == []
    assert provenance.machine(ZEN4)["bf16_flags"] == ["avx512_bf16"]


def test_the_learner_record_says_bf16_ran_fp32_and_why():
    fell_back = provenance.learner_record("bf16", {"lanes": 1.0, "bf16": 0.0, "fused": 0.0})
    assert fell_back["precision_asked"] == "bf16" and fell_back["precision"] == "fp32"
    assert "no native bf16" in fell_back["why"] and fell_back["fused_kernel"] is False
    native = provenance.learner_record("bf16", {"bf16": 1.0, "fused": 1.0})
    assert native == {"precision_asked": "bf16", "precision": "bf16", "fused_kernel": True}
    assert provenance.learner_record("fp32", {}) == {"precision_asked": "fp32", "precision": "fp32"}


def test_code_is_this_checkouts_commit_and_none_outside_git(tmp_path):
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True)
    got = provenance.code()
    if head.returncode == 0:
        assert got["commit"] == head.stdout.decode().strip()
        assert isinstance(got["dirty"], bool)
    assert provenance.code(tmp_path) == {"commit": None, "dirty": None}
    # A copy inside someone else's repository is not that repository's commit.
    subprocess.run(["git", "init", "-q", str(tmp_path)], check=True)
    subprocess.run(
        ["git", "-C", str(tmp_path), "-c", "user.name=t", "-c", "user.email=t@t"]
        + ["commit", "-q", "--allow-empty", "-m", "t"],
        check=True,
    )
    assert provenance.code(tmp_path)["commit"] is not None  # its own top: its commit
    (tmp_path / "copy").mkdir()
    assert provenance.code(tmp_path / "copy") == {"commit": None, "dirty": None}


@pytest.mark.parametrize("text", ["{", "[]", '{"starts": 3}', '{"starts": [1]}'])
def test_a_file_that_is_not_a_record_is_refused_by_name(tmp_path, text):
    path = tmp_path / provenance.FILE
    path.write_text(text)
    with pytest.raises(provenance.ProvenanceError, match=re.escape(str(path))):
        provenance.append(path, {"role": "trainer"})
    assert path.read_text() == text  # nothing lost


def test_append_keeps_every_start_and_write_replaces_them(tmp_path):
    path = tmp_path / provenance.FILE
    assert provenance.read(path) == []
    provenance.append(path, {"n": 1})
    assert provenance.append(path, {"n": 2}) == [{"n": 1}, {"n": 2}]
    provenance.write(path, [{"n": 3}])
    assert json.loads(path.read_text()) == {"starts": [{"n": 3}]}


def test_a_trainer_run_records_bf16_running_fp32_without_native_bf16(tmp_path, monkeypatch):
    """The config keeps what was asked (bf16); the record says what ran (fp32)."""
    monkeypatch.setattr(precision, "native_bf16", lambda: False)
    train(make_config({**SMALL, "precision": "bf16"}), tmp_path, progress=False)
    (start,) = provenance.read(tmp_path / provenance.FILE)
    assert json.loads((tmp_path / "config.json").read_text())["precision"] == "bf16"
    assert start["role"] == "trainer"
    assert start["learner"]["precision"] == "fp32" and "why" in start["learner"]
    assert start["packages"]["torch"] == torch.__version__ and start["torch_threads"] >= 1
    assert start["machine"]["cpus"] >= 1 and start["started"].endswith("Z")


def test_a_resume_adds_its_start_and_a_fresh_run_starts_over(tmp_path):
    cfg = make_config(SMALL)
    train(cfg, tmp_path, progress=False, cut_every_s=0, stop_when=lambda r: r["episode"] == 2)
    train(cfg, tmp_path, progress=False, cut_every_s=0, resume=True)
    starts = provenance.read(tmp_path / provenance.FILE)
    assert [s["role"] for s in starts] == ["trainer", "trainer"]
    for s in starts:
        assert s["learner"]["precision_asked"] == s["learner"]["precision"] == "fp32"
        assert "why" not in s["learner"]
    train(cfg, tmp_path, progress=False)  # not a resume: its own record
    assert len(provenance.read(tmp_path / provenance.FILE)) == 1


def test_a_resume_refuses_a_corrupt_record_naming_it_and_changes_nothing(tmp_path, capsys):
    cfg = make_config(SMALL)
    train(cfg, tmp_path, progress=False, cut_every_s=0, stop_when=lambda r: r["episode"] == 2)
    path = tmp_path / provenance.FILE
    path.write_text("not json")
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    with pytest.raises(CutError, match=re.escape(str(path))):
        train(cfg, tmp_path, progress=False, resume=True)
    assert main(["train", "--resume", str(tmp_path), "--quiet"]) == 2
    assert str(path) in capsys.readouterr().err
    after = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    assert after == before
