"""GET /presets: the shipped configs and every config key, for the dashboard's form."""

from __future__ import annotations

import httpx

from shared.config import TrainConfig
from tests.harness import ROOT, start_api


def test_presets_are_the_shipped_configs_and_every_key(tmp_path):
    """GET /presets: each YAML file under the configs dir as written (the dashboard's
    form starts from one); a file that does not read is left out, not half-served."""
    import yaml

    server = start_api(tmp_path, None)
    try:
        out = httpx.get(f"{server.url}/presets").json()
    finally:
        server.stop()
    presets = {p["name"]: p["config"] for p in out["presets"]}
    shipped = sorted((ROOT / "configs").rglob("*.yaml"))
    assert sorted(presets) == sorted(
        p.relative_to(ROOT / "configs").with_suffix("").as_posix() for p in shipped
    )
    assert presets["default"] == yaml.safe_load((ROOT / "configs/default.yaml").read_text())
    assert presets["fig8/sparse-cen-macb"]["seeds"] == [0, 1, 2]
    assert [k["name"] for k in out["keys"]] == list(TrainConfig.model_fields)
    assert {k["name"]: k["default"] for k in out["keys"]}["hidden"] == [400, 300]
    mine = tmp_path / "mine"
    (mine / "sub").mkdir(parents=True)
    (mine / "sub" / "a.yaml").write_text("task: spread\nagents: 3\n")
    (mine / "broken.yaml").write_text("task: [unclosed\n")
    server = start_api(tmp_path, None, configs_dir=mine)
    try:
        out = httpx.get(f"{server.url}/presets").json()
    finally:
        server.stop()
    assert out["presets"] == [{"name": "sub/a", "config": {"task": "spread", "agents": 3}}]
