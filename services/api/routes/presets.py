"""The shipped configs as presets (the dashboard's experiment form starts from one) and
the config keys with their defaults, so a client can offer every key."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from fastapi import APIRouter, Request
from pydantic import BaseModel, Field

from shared.config import ConfigError, TrainConfig, read_config_file

router = APIRouter(tags=["presets"])
log = logging.getLogger("macb.api")


class Preset(BaseModel):
    name: str = Field(description="the file under configs/, without .yaml (fig8/sparse)")
    config: dict[str, Any] = Field(description="the file's mapping as written (seeds too)")


class ConfigKey(BaseModel):
    name: str
    default: Any
    description: str | None = None


class Presets(BaseModel):
    presets: list[Preset]
    keys: list[ConfigKey] = Field(description="every config key, in the schema's order")


def read_presets(root: Path) -> list[dict[str, Any]]:
    """Every YAML file under `root`, sorted by name; a file that does not read is left
    out (and logged), not served half-read."""
    out = []
    for path in sorted(root.rglob("*.yaml")):
        try:
            config = read_config_file(path)
        except (ConfigError, OSError) as err:
            log.warning("preset %s left out: %s", path, err)
            continue
        out.append({"name": path.relative_to(root).with_suffix("").as_posix(), "config": config})
    return out


@router.get("/presets", response_model=Presets)
def list_presets(request: Request):
    """The shipped configs (configs/*.yaml, `MACB_API_CONFIGS_DIR`) and the config keys."""
    keys = [
        {"name": n, "default": f.default, "description": f.description}
        for n, f in TrainConfig.model_fields.items()
    ]
    return {"presets": read_presets(request.app.state.settings.presets_dir), "keys": keys}
