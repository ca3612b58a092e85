"""Every `MACB_*` environment variable of the services, the CLI and the learners, in one
class (the API's own `MACB_API_*` server settings are `services.api.main.Settings`).

`settings()` reads the environment when called, not at import: tests and `macb up`'s
supervisor set variables per process (and a test may change one between two calls),
so nothing here is frozen in a module constant. docs/deploy.md's table of variables
is kept equal to `Settings`' fields by tests/test_settings.py.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

PREFIX = "MACB_"


class Settings(BaseSettings):
    """One process's `MACB_*` settings; each field is read from MACB_<NAME>."""

    model_config = SettingsConfigDict(env_prefix=PREFIX, extra="ignore")

    # ---------------------------------------------------------------- the bus
    zenoh_connect: str | None = Field(
        None, description="router endpoints, comma-separated (default tcp/127.0.0.1:7447)"
    )
    zenoh_listen: str | None = Field(
        None, description="where `macb serve router` listens (default tcp/127.0.0.1:7447)"
    )
    zenoh_secrets: str | None = Field(
        None, description="a folder as `macb certs` writes it: TLS files and passwords by user"
    )
    zenoh_user: str | None = Field(None, description="this session's user (its service id)")
    zenoh_password: str | None = Field(None, description="its password")
    zenoh_password_file: str | None = Field(None, description="a file holding its password")
    zenoh_users_file: str | None = Field(None, description="a router's user:password file")
    zenoh_tls_ca: str | None = Field(None, description="the CA certificate (turns TLS on)")
    zenoh_tls_cert: str | None = Field(None, description="this session's certificate")
    zenoh_tls_key: str | None = Field(None, description="its private key")
    zenoh_mtls: str | None = Field(None, description="1: routers also check clients' certificates")
    # ---------------------------------------------------------------- watching runs
    peer_grace_s: float = Field(
        30.0, description="how long a lost service may take to come back before its runs fail"
    )
    # ---------------------------------------------------------------- services
    restarts: int = Field(0, description="set by `macb up`'s supervisor: this service's restarts")
    # shared/procs.py reads this one itself (standard library only), first thing in `macb`.
    parent_pid: int | None = Field(
        None, description="set by `macb up`'s supervisor: the PID this service dies with"
    )
    node: str | None = Field(
        None, description="the node this service runs on (default SLURMD_NODENAME, else the host)"
    )
    # cli/forkserver.py reads this one itself, from the environment it starts a service with.
    fork_server: str = Field(
        "", description="0, off, false or no: `macb up` starts each service as its own interpreter"
    )
    learner_cut_s: float = Field(30.0, description="a learner's cut every this many seconds")
    counter_snapshot_s: float = Field(
        5.0, description="a counter's snapshot every this many seconds"
    )
    # The interpreter's default (5 ms) lets the counter's ingest thread hold the GIL for a
    # whole slice while a bonus query waits on Zenoh's thread.
    counter_switch_s: float = Field(
        0.0005, description="the counter process's thread switch interval, seconds"
    )
    evaluator_nice: int = Field(0, description="a lower CPU priority for the evaluator")
    # ---------------------------------------------------------------- learners
    # shared/core/learners/fused.py reads these two itself (shared.core imports numpy
    # and torch only, not pydantic); they are here to be documented and checked alike.
    fused: str = Field("", description="0, off, false or no: the bf16 learner's fused kernel off")
    kernel_cache: Path | None = Field(
        None, description="where the fused kernel is built (default ~/.cache/macb/kernels)"
    )
    # ---------------------------------------------------------------- run groups
    # shared/run/heap.py reads this one itself (shared.run does not import settings).
    steady_heap: str = Field(
        "", description="0, off, false or no: a training process leaves glibc's malloc thresholds"
    )
    group_timing: str | None = Field(
        None,
        description="a folder: each run group writes its time split at every point there "
        "(benchmarks/bench_fig8.py)",
    )
    # ---------------------------------------------------------------- the API's clients
    configs_dir: Path | None = Field(
        None,
        description="the shipped configs/ folder (the thesis's figures' arms, the "
        "dashboard's presets); default: the checkout's, else ./configs",
    )
    api_url: str | None = Field(None, description="the API `macb run/ls/stop/reproduce` call")
    api_token: str | None = Field(
        None, description="the bearer token they send (the server reads it too)"
    )

    @classmethod
    def env_name(cls, field: str) -> str:
        """The variable that sets `field`."""
        if field not in cls.model_fields:
            raise KeyError(field)
        return PREFIX + field.upper()

    @classmethod
    def of(cls, env: Mapping[str, str]) -> Settings:
        """The settings `env` gives, and the defaults for the rest: the process's own
        environment is not read (`Security.from_env` checks an explicit mapping)."""
        values: dict[str, Any] = {}
        for name, info in cls.model_fields.items():
            raw = env.get(cls.env_name(name))
            values[name] = raw if raw is not None else info.get_default(call_default_factory=True)
        return cls(**values)


def node_name() -> str:
    """The node a service says it runs on: MACB_NODE, else Slurm's name for the node
    (SLURMD_NODENAME, set in every Slurm task), else the host name. The scheduler gives
    a run the counter (and actors, evaluator) on its learner's node by this name."""
    import os
    import socket

    try:
        explicit = settings().node
    except ValueError:
        explicit = None
    return explicit or os.environ.get("SLURMD_NODENAME") or socket.gethostname().split(".")[0]


def shipped_configs() -> Path:
    """The configs/ folder the figures' arms and the dashboard's presets are read from:
    MACB_CONFIGS_DIR; else the checkout's beside these packages (a source or editable
    install); else ./configs (an image's working folder holds it: the wheel has no
    configs, which are no package)."""
    given = settings().configs_dir
    if given is not None:
        return given
    checkout = Path(__file__).resolve().parents[1] / "configs"
    return checkout if checkout.is_dir() else Path("configs")


def settings() -> Settings:
    """The `MACB_*` variables as they are now (a malformed one raises, naming it)."""
    return Settings()
