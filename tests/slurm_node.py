"""A real one-node Slurm for `make test-slurm` (tests/test_slurm.py): Debian's munge and
slurm-wlm, installed when missing (as root, with MACB_SLURM_SETUP=1), started in a
folder of the test's own and stopped after.

Everything lives in that folder: a munge key and socket of its own (slurm.conf's
`AuthInfo=socket=...`), slurm.conf on free ports, state, spool and logs, so nothing of a
Slurm or munge the machine may already run is touched. Commands reach this Slurm
through `SLURM_CONF` in `Node.env` (sbatch, squeue, sinfo, scontrol, scancel read it,
and the jobs inherit it). The node is this machine: `hostname -s`, its CPUs,
`select/cons_tres` by CPU, `proctrack/linuxproc` (no cgroups needed).
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

from cli.supervisor import free_port

PACKAGES = ("munge", "slurm-wlm")
DAEMONS = ("/usr/sbin/munged", "/usr/sbin/slurmctld", "/usr/sbin/slurmd")
PARTITION = "macbtest"


class Unavailable(RuntimeError):
    """No Slurm can run here (the reason says why)."""


def install(may_set_up: bool) -> None:
    """munge and slurm-wlm from the package registry, when missing and allowed."""
    if all(Path(d).exists() for d in DAEMONS) and shutil.which("sbatch"):
        return
    if not may_set_up:
        raise Unavailable("munge / slurm-wlm not installed (make test-slurm installs them)")
    if os.geteuid() != 0 or not shutil.which("apt-get"):
        raise Unavailable("munge / slurm-wlm missing, and installing them needs root and apt-get")
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    for argv in (["apt-get", "update", "-qq"], ["apt-get", "install", "-y", "-qq", *PACKAGES]):
        got = subprocess.run(argv, capture_output=True, text=True, env=env, timeout=900)
        if got.returncode:
            raise Unavailable(f"{' '.join(argv)} failed: {got.stderr[-2000:]}")


def slurm_conf(folder: Path, host: str, cpus: int, ctl_port: int, node_port: int) -> str:
    """A one-node slurm.conf with every path in `folder`."""
    return f"""\
ClusterName=macbtest
SlurmctldHost={host}
SlurmctldPort={ctl_port}
SlurmdPort={node_port}
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket={folder / "munge.socket"}
StateSaveLocation={folder / "state"}
SlurmdSpoolDir={folder / "spool"}
SlurmctldPidFile={folder / "slurmctld.pid"}
SlurmdPidFile={folder / "slurmd.pid"}
SlurmctldLogFile={folder / "slurmctld.log"}
SlurmdLogFile={folder / "slurmd.log"}
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
MpiDefault=none
ReturnToService=2
SchedulerType=sched/backfill
SchedulerParameters=sched_interval=2
MinJobAge=3600
KillWait=5
NodeName={host} CPUs={cpus} State=UNKNOWN
PartitionName={PARTITION} Nodes={host} Default=YES MaxTime=INFINITE State=UP
"""


@dataclass
class Node:
    """A running one-node Slurm: its folder, the environment its commands need, and the
    daemons' processes (stopped by `stop`)."""

    folder: Path
    env: dict[str, str]
    procs: list[subprocess.Popen] = field(default_factory=list)

    def run(self, *argv: str, timeout: float = 60) -> subprocess.CompletedProcess:
        return subprocess.run(
            list(argv), capture_output=True, text=True, env=self.env, timeout=timeout
        )

    def logs(self) -> str:
        parts = []
        for name in ("slurmctld.log", "slurmd.log", "munged.log"):
            path = self.folder / name
            if path.exists():
                parts.append(f"--- {name}\n" + "\n".join(path.read_text().splitlines()[-30:]))
        return "\n".join(parts)

    def stop(self) -> None:
        """Stops the daemons this node started, by their PIDs."""
        for p in reversed(self.procs):
            if p.poll() is None:
                p.terminate()
        for p in reversed(self.procs):
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def start(folder: Path, may_set_up: bool) -> Node:
    """Installs (if allowed and missing), configures and starts munged, slurmctld and
    slurmd in `folder`; returns once `sinfo` shows the node idle."""
    install(may_set_up)
    if os.geteuid() != 0:
        raise Unavailable("the test's slurmd must run as root (it starts jobs as their user)")
    for sub in ("state", "spool"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    folder.chmod(0o755)
    key = folder / "munge.key"
    key.write_bytes(os.urandom(1024))
    key.chmod(0o600)
    host = socket.gethostname().split(".")[0]
    conf = folder / "slurm.conf"
    conf.write_text(slurm_conf(folder, host, os.cpu_count() or 1, free_port(), free_port()))
    env = {**os.environ, "SLURM_CONF": str(conf)}
    node = Node(folder, env)
    munged = [
        "/usr/sbin/munged", "--foreground", "--force", f"--key-file={key}",
        f"--socket={folder / 'munge.socket'}", f"--pid-file={folder / 'munged.pid'}",
        f"--log-file={folder / 'munged.log'}", f"--seed-file={folder / 'munged.seed'}",
    ]  # fmt: skip
    try:
        for argv in (munged, ["/usr/sbin/slurmctld", "-D", "-i"], ["/usr/sbin/slurmd", "-D"]):
            log = (folder / f"{Path(argv[0]).name}.out").open("w")
            node.procs.append(subprocess.Popen(argv, env=env, stdout=log, stderr=subprocess.STDOUT))
            time.sleep(0.5)
            if node.procs[-1].poll() is not None:
                raise Unavailable(f"{argv[0]} exited at once:\n{node.logs()}")
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            got = node.run("sinfo", "-h", "-o", "%T")
            if got.returncode == 0 and got.stdout.strip() == "idle":
                return node
            time.sleep(0.5)
        raise Unavailable(f"the node did not come up idle:\n{node.logs()}")
    except BaseException:
        node.stop()
        raise
