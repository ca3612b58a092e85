"""The `MACB_*` variables in one class (shared/settings.py): read when used, an explicit
mapping read alone, a malformed value refused by name, and docs/deploy.md's table of
variables equal to the class's fields."""

from __future__ import annotations

import inspect
import re
from pathlib import Path

import pytest
from pydantic import ValidationError

from shared.core.learners import fused
from shared.net.bus import DEFAULT_ENDPOINT, default_connect
from shared.net.monitor import Graces, peer_grace_s
from shared.net.security import ENV, Security
from shared.settings import Settings, settings

ROOT = Path(__file__).resolve().parent.parent


def test_a_variable_is_read_when_used_not_when_imported(monkeypatch):
    monkeypatch.delenv("MACB_PEER_GRACE_S", raising=False)
    monkeypatch.delenv("MACB_ZENOH_CONNECT", raising=False)
    assert peer_grace_s() == Graces().peer_s == 30.0
    assert default_connect() == [DEFAULT_ENDPOINT]
    monkeypatch.setenv("MACB_PEER_GRACE_S", "2.5")
    monkeypatch.setenv("MACB_ZENOH_CONNECT", "tcp/127.0.0.1:1, tcp/127.0.0.1:2")
    assert peer_grace_s() == 2.5
    assert default_connect() == ["tcp/127.0.0.1:1", "tcp/127.0.0.1:2"]


def test_an_explicit_mapping_is_read_alone(monkeypatch):
    monkeypatch.setenv("MACB_ZENOH_USER", "from-the-process")
    monkeypatch.setenv("MACB_LEARNER_CUT_S", "7")
    s = Settings.of({"MACB_ZENOH_USER": "actor0", "OTHER": "x"})
    assert (s.zenoh_user, s.learner_cut_s) == ("actor0", 30.0)
    assert settings().zenoh_user == "from-the-process" and settings().learner_cut_s == 7.0
    assert Security.from_env({"MACB_ZENOH_USER": "actor0"}).user == "actor0"
    assert Security.from_env({"MACB_ZENOH_USER": ""}).user is None  # empty: unset


def test_a_malformed_value_is_refused_naming_its_variable(monkeypatch):
    monkeypatch.setenv("MACB_COUNTER_SNAPSHOT_S", "soon")
    with pytest.raises(ValidationError, match="counter_snapshot_s"):
        settings()


def test_every_name_is_its_fields_variable():
    assert Settings.env_name("peer_grace_s") == "MACB_PEER_GRACE_S"
    assert Settings.env_name("fused") == fused.ENV_SWITCH  # read by shared.core itself
    assert "MACB_KERNEL_CACHE" in inspect.getsource(fused.cache_dir)
    assert ENV["tls_ca"] == "MACB_ZENOH_TLS_CA"
    assert set(ENV.values()) <= {Settings.env_name(f) for f in Settings.model_fields}
    with pytest.raises(KeyError):
        Settings.env_name("no_such_setting")


def test_the_deploy_doc_has_one_row_per_variable_and_no_other():
    doc = (ROOT / "docs" / "deploy.md").read_text()
    table = doc.split("<!-- settings:", 1)[1].split("\n\n", 1)[0]
    rows = [line for line in table.splitlines() if line.startswith("| `MACB_")]
    named = [name for row in rows for name in re.findall(r"`(MACB_\w+)`", row.split("|")[1])]
    assert len(named) == len(set(named))
    assert set(named) == {Settings.env_name(f) for f in Settings.model_fields}


def test_the_api_doc_has_one_row_per_api_setting_and_no_other():
    """docs/api.md's table of `MACB_API_*` variables: one row per field of the API's
    Settings, each named as pydantic-settings reads it (its env_prefix)."""
    from services.api.main import Settings as ApiSettings

    doc = (ROOT / "docs" / "api.md").read_text()
    table = doc.split("<!-- api settings:", 1)[1].split("\n\n", 1)[0]
    named = re.findall(r"^\| `(MACB_API_\w+)`", table, flags=re.M)
    assert len(named) == len(set(named))
    prefix = ApiSettings.model_config["env_prefix"]
    assert set(named) == {f"{prefix}{f}".upper() for f in ApiSettings.model_fields}
