"""The wheel, as the Dockerfile builds and installs it (not editable): every file the code
reads beside itself must be in it, or every container (compose, Kubernetes) fails where
it reads one; the dashboard and the figure view once answered 500 there because
charts.js and figure.html were left out.

The wheel is built offline from a copy of what the Dockerfile copies into /src, so the
checkout gets no build/ or egg-info of its own.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
# Files in the packages that no code reads, and why they need not ship.
NOT_READ = {
    "examples/fig8-campaign.sh": "a script run from a pinned checkout (its head says so)",
}


def dockerfile_sources() -> list[str]:
    """What the Dockerfile copies into /src, from which it installs the wheel."""
    found: list[str] = []
    for line in (ROOT / "Dockerfile").read_text().splitlines():
        words = line.split()
        if len(words) >= 3 and words[0] == "COPY" and words[-1].startswith("/src"):
            found += words[1:-1]
    return found


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> tuple[Path, set[str]]:
    """(the wheel unpacked, the names in it), built with no network and no isolation."""
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    src.mkdir()
    for name in dockerfile_sources():
        path = ROOT / name
        if path.is_dir():
            shutil.copytree(path, src / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(path, src / name)
    out = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
         "--no-index", "--quiet", "--wheel-dir", str(tmp / "dist"), str(src)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-3000:]
    (built,) = (tmp / "dist").glob("macb-*.whl")
    with zipfile.ZipFile(built) as zf:
        zf.extractall(tmp / "unpacked")
        return tmp / "unpacked", set(zf.namelist())


def test_the_dockerfile_copies_every_package():
    packages = {p.parent.name for p in ROOT.glob("*/__init__.py")} - {"tests"}
    assert packages <= set(dockerfile_sources()), dockerfile_sources()


def test_every_file_the_code_reads_is_in_the_wheel(wheel):
    """Every non-Python file in the packages (html, js, the bf16 kernel's C source) is in
    the wheel, but the ones listed as never read."""
    _, names = wheel
    data = {
        p.relative_to(ROOT).as_posix()
        for d in dockerfile_sources()
        if (ROOT / d).is_dir()
        for p in (ROOT / d).rglob("*")
        if p.is_file() and p.suffix not in (".py", ".pyc") and "__pycache__" not in p.parts
    }
    assert {"services/api/charts.js", "shared/core/learners/master.c"} <= data
    assert set(NOT_READ) <= data, "NOT_READ names a file that is gone"
    missing = sorted(data - set(NOT_READ) - names)
    assert missing == [], f"not in the wheel (pyproject.toml, package-data): {missing}"


def test_the_pages_render_from_the_installed_wheel(wheel):
    """The API's dashboard and the figure view (also `macb view`'s) read from the wheel
    alone, the charts' script inlined, as a container serves them."""
    unpacked, _ = wheel
    code = (
        "import sys; sys.path.insert(0, sys.argv[1])\n"
        "from services.api import pages\n"
        "assert pages.__file__.startswith(sys.argv[1]), pages.__file__\n"
        "for name in ('dashboard.html', 'figure.html'):\n"
        "    html = pages.page(name)\n"
        "    assert pages.SCRIPT_TAG not in html and '<script>' in html, name\n"
        "print('ok')\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code, str(unpacked)],
        cwd=unpacked,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-3000:]
    # the bf16 learner's kernel is found where fused.py looks for it
    fused = (unpacked / "shared/core/learners/fused.py").read_text()
    (name,) = re.findall(r'with_name\("([^"]+)"\)', fused)
    assert (unpacked / "shared/core/learners" / name).is_file()


def test_the_figures_arms_are_read_from_the_configs_folder_an_image_gives(wheel, tmp_path):
    """The wheel holds no configs/ (no package): from it, the figures' arm files (the
    API's figure view, `macb reproduce`) are read from MACB_CONFIGS_DIR, as the image
    sets it, or ./configs; with neither, a clear error names the folder and the way."""
    from cli.reproduce.figures import FIGURES

    unpacked, _ = wheel
    arms = str(len(FIGURES["fig8"].arms))
    shutil.copytree(ROOT / "configs", tmp_path / "copy")
    code = (
        "import sys; sys.path.insert(0, sys.argv[1])\n"
        "from cli.reproduce import experiments\n"
        "from cli.reproduce.figures import FIGURES\n"
        "assert experiments.__file__.startswith(sys.argv[1]), experiments.__file__\n"
        "try:\n"
        "    print(len(experiments.arm_configs(FIGURES['fig8'])))\n"
        "except FileNotFoundError as err:\n"
        "    print('refused:', err)\n"
    )

    def run(cwd: Path, env: dict) -> str:
        out = subprocess.run(
            [sys.executable, "-c", code, str(unpacked)],
            cwd=cwd,
            env={**os.environ, **env},
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert out.returncode == 0, out.stderr[-3000:]
        return out.stdout.strip()

    empty = tmp_path / "empty"
    empty.mkdir()
    given = {"MACB_CONFIGS_DIR": str(tmp_path / "copy")}
    assert run(empty, given) == arms
    shutil.copytree(ROOT / "configs", empty / "configs")
    assert run(empty, {}) == arms  # ./configs, as the image's WORKDIR holds it
    shutil.rmtree(empty / "configs")
    said = run(empty, {})
    assert said.startswith("refused:") and "MACB_CONFIGS_DIR" in said, said
