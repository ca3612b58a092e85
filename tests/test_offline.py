"""docker/offline.py's rules that need no docker: one place for pins, what the image's
tag covers, and where the torch wheel comes from (tests/test_compose.py builds with it)."""

from __future__ import annotations

import re
import shutil
import tomllib

import pytest

from tests.conftest import ROOT, offline


def test_the_torch_pin_is_pyproject_s_and_the_dockerfile_names_no_version():
    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    assert offline.torch_pin() in deps
    dockerfile = (ROOT / "Dockerfile").read_text()
    assert not re.search(r"==\s*\d", dockerfile), "every pin comes from pyproject.toml"
    assert "ARG BASE_IMAGE=python:3.11-slim" in dockerfile
    assert 'ARG TORCH_SOURCE="--index-url https://download.pytorch.org/whl/cpu"' in dockerfile


def test_the_build_context_is_what_the_image_needs():
    files = {str(p.relative_to(ROOT)) for p in offline.context_files()}
    assert {"pyproject.toml", "README.md", "cli/main.py", "configs/default.yaml"} <= files
    assert "services/api/dashboard.html" in files
    assert not any(f.startswith((".venv/", "runs/", "data/", "tests/", ".git/")) for f in files)
    assert not any("__pycache__" in f for f in files)


def _tree(tmp_path):
    """A copy of the files the digest reads, with one source file of its own."""
    root = tmp_path / "repo"
    root.mkdir()
    for name in ("Dockerfile", ".dockerignore", "pyproject.toml", "README.md"):
        shutil.copyfile(ROOT / name, root / name)
    for d in ("shared", "services", "cli", "configs", "docker/local"):
        (root / d).mkdir(parents=True)
    (root / "shared" / "a.py").write_text("x = 1\n")
    return root


def test_the_tag_changes_with_any_input_and_only_then(tmp_path):
    root = _tree(tmp_path)
    args = {"BASE_IMAGE": "macb-base:x"}
    first = offline.context_digest("sha256:1", args, root)
    assert offline.context_digest("sha256:1", args, root) == first, "same inputs, same tag"
    (root / "shared" / "__pycache__").mkdir()
    (root / "shared" / "__pycache__" / "a.cpython-311.pyc").write_bytes(b"\0")
    (root / "tests").mkdir()
    (root / "tests" / "t.py").write_text("not in the context\n")
    assert offline.context_digest("sha256:1", args, root) == first, "caches and tests don't count"
    assert offline.context_digest("sha256:2", args, root) != first, "another base"
    assert offline.context_digest("sha256:1", {**args, "PIP_CA": "c"}, root) != first
    (root / "shared" / "a.py").write_text("x = 2\n")
    assert offline.context_digest("sha256:1", args, root) != first, "a source changed"


def test_the_torch_wheel_is_found_where_pip_s_find_links_says():
    try:
        wheel = offline.torch_wheel()
    except offline.Unavailable as err:
        pytest.skip(f"not a project machine: {err}")
    version = offline.torch_pin().split("==")[1]
    assert wheel.name.startswith(f"torch-{version}+cpu-cp311-") and wheel.is_file()
    assert wheel.parent in offline.find_links()
