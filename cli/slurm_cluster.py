"""`macb up --launcher slurm`: the service cluster as one Slurm job, on one bus.

The batch script (written to DATA_DIR/.slurm/, then submitted) runs, in one allocation
of `--nodes` nodes with `--slots` tasks of `--cpus-per-slot` CPUs on each:

- on the first node (the batch step): the router and the API;
- on every node, one `srun` step task: a counter, `counter-nI` (I: Slurm's node index),
  its data in DATA_DIR/counter-nI;
- on every node, one `srun` step task per slot: `macb serve slot --id sK` (K: the task's
  rank), a learner, an evaluator and `--actors` actors restarted when they die.

Every service names its node (Slurm's SLURMD_NODENAME, `shared.settings.node_name`), so
the API's scheduler gives a run the counter, evaluator and actors on its learner's node
and its lockstep round trips stay there; an experiment posted to the API spreads its runs
over the slots. On one node the bus is plain TCP on loopback (or TLS with --secrets); on
several it must be the secure bus of docs/deploy.md (--secrets): the router listens on
`tls/0.0.0.0:PORT`, every service signs in as its id, the users all known before the job
starts. The job runs until its time limit or `scancel`, which ends every process of it;
a part of it that ends ends the job (`wait -n`, and `srun --kill-on-bad-exit=1`: without
it srun waits for a step's other tasks when one fails).

The router's and the API's ports must be free on the first node before either starts,
and the router must still be ours when its port answers: otherwise the job's services
would join whichever cluster listens there. The API without MACB_API_TOKEN listens on
127.0.0.1 of the first node, which `wait_until_up` polls only from that node itself
(otherwise it says how to reach it); with a token it sends it.
"""

from __future__ import annotations

import argparse
import ipaddress
import shlex
import socket
import sys
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import urlparse

from cli.reproduce.slurm import (
    Runner,
    SlurmOptions,
    directive,
    directive_path_error,
    macb_argv,
    parse_job_id,
    placement,
    preflight,
    run_command,
    sbatch_argv,
)
from cli.supervisor import THREAD_ENV

if TYPE_CHECKING:
    from services.api.client import ApiClient

JOB_NAME = "macb-cluster"


@dataclass(frozen=True)
class ClusterJob:
    """What the job runs: `slots` slots of `cpus` CPUs on each of `nodes` nodes."""

    nodes: int
    slots: int  # per node
    cpus: int  # per slot
    actors: int  # per slot
    data_dir: Path
    router_port: int = 7447
    api_port: int = 8000
    secrets: Path | None = None
    api_public: bool = False  # the API on all interfaces (MACB_API_TOKEN set)
    group_size: int = 1

    @property
    def log_dir(self) -> Path:
        return self.data_dir / ".slurm"

    def users(self) -> list[str]:
        """Every bus user the job signs in as (each must be in the secrets' users.txt)."""
        out = ["router", "api"] + [f"counter-n{i}" for i in range(self.nodes)]
        for k in range(self.nodes * self.slots):
            out += [f"learner-s{k}", f"evaluator-s{k}"]
            out += [f"actor-s{k}" + (f"-{r}" if r else "") for r in range(self.actors)]
        return out

    @property
    def services(self) -> int:
        """The services that announce themselves once it is up (the router does not)."""
        return len(self.users()) - 1

    def error(self) -> str | None:
        """Why this job cannot be submitted, or None."""
        for name, value in (("--nodes", self.nodes), ("--slots", self.slots)):
            if value < 1:
                return f"{name} must be at least 1, not {value}"
        if self.cpus < 1 or self.actors < 1:
            return "--cpus-per-slot and --actors must be at least 1"
        if self.nodes > 1 and self.secrets is None:
            return (
                f"--nodes {self.nodes}: off one node the bus must be the secure one "
                "(docs/deploy.md): give --secrets DIR, a folder `macb certs` wrote"
            )
        if self.secrets is not None:
            users = self.secrets / "users.txt"
            try:
                known = {line.split(":", 1)[0] for line in users.read_text().splitlines()}
            except OSError as err:
                return f"--secrets: cannot read {users} ({err.strerror or err})"
            if missing := [u for u in self.users() if u not in known]:
                return (
                    f"--secrets: {users} lacks the job's users {', '.join(missing)}; add them: "
                    f"macb certs {self.secrets} " + " ".join(f"--user {u}" for u in missing)
                )
        return None


def render_cluster_script(job: ClusterJob, macb: list[str], cwd: Path, opts: SlurmOptions) -> str:
    """The batch script of `job` (see the module)."""
    n, per_node = job.nodes, job.slots
    secure = job.secrets is not None
    listen = f"tls/0.0.0.0:{job.router_port}" if n > 1 else f"tcp/127.0.0.1:{job.router_port}"
    connect = "tls/$HEAD:$PORT" if n > 1 else "tcp/127.0.0.1:$PORT"
    if secure and n == 1:
        listen, connect = f"tls/127.0.0.1:{job.router_port}", "tls/127.0.0.1:$PORT"
    http = "0.0.0.0" if job.api_public else "127.0.0.1"
    url = "http://$HEAD:$API_PORT" if job.api_public else "http://127.0.0.1:$API_PORT"
    user = (lambda u: f"MACB_ZENOH_USER={u} ") if secure else (lambda u: "")
    counter_user = 'export MACB_ZENOH_USER="$id"; ' if secure else ""
    lines = [
        "#!/bin/bash",
        f"#SBATCH --job-name={JOB_NAME}",
        f"#SBATCH --nodes={n}",
        f"#SBATCH --ntasks-per-node={per_node}",
        f"#SBATCH --cpus-per-task={job.cpus}",
        # a requeued job (a node lost: Slurm requeues batch jobs by default) appends to
        # the log rather than truncating the failed attempt's
        "#SBATCH --open-mode=append",
        directive("output", f"{job.log_dir}/cluster-%j.log"),
        directive("chdir", str(cwd)),
    ]
    lines += placement(opts)
    thread_env = " ".join(f"{k}={v}" for k, v in THREAD_ENV.items())
    lines += [
        "# Written by `macb up --launcher slurm` (docs/deploy.md, 'On a Slurm cluster'): the",
        "# service cluster in one allocation. The first node (this batch step) runs the router",
        "# and the API; an srun step runs a counter on every node, another one worker slot",
        "# (learner, evaluator, actors) per task. scancel ends them all.",
        "set -uo pipefail",
        f"MACB=({shlex.join(macb)})",
        f"DATA={shlex.quote(str(job.data_dir))}",
        f"LOGS={shlex.quote(str(job.log_dir))}",
        f"PORT={job.router_port}",
        f"API_PORT={job.api_port}",
        "HEAD=$(hostname -s)",
        f"export {thread_env} PYTHONUNBUFFERED=1",
        f"export MACB_ZENOH_CONNECT={connect}",
    ]
    if secure:
        lines.append(f"export MACB_ZENOH_SECRETS={shlex.quote(str(job.secrets))}")
    job_says = 'echo "macb cluster job $SLURM_JOB_ID:'
    lines += [
        'mkdir -p "$DATA"',
        'echo "$HEAD" > "$LOGS/$SLURM_JOB_ID.head"',
        'echo "macb cluster job $SLURM_JOB_ID on $SLURM_JOB_NODELIST: router and API on $HEAD,'
        ' $SLURM_NTASKS slot(s), bus $MACB_ZENOH_CONNECT"',
        "# the router's and the API's ports free: else whoever listens there answers for them",
        "# (a service on every address is probed on this node's name too: a listener on",
        "# its address alone does not answer on loopback)",
        f"for p in {'$PORT@$HEAD' if n > 1 else '$PORT'} "
        f"{'$API_PORT@$HEAD' if job.api_public else '$API_PORT'}; do",
        '    port=${p%@*}; hosts=127.0.0.1; [[ $p == *@* ]] && hosts="127.0.0.1 ${p#*@}"',
        "    for h in $hosts; do",
        "        if (exec 3<>/dev/tcp/$h/$port) 2>/dev/null; then",
        f"            {job_says} port $port on $HEAD is in use: something listens on it"
        ' (another cluster?); not starting" >&2',
        "            exit 2",
        "        fi",
        "    done",
        "done",
        f'{user("router")}"${{MACB[@]}}" serve router --listen {listen} &',
        "ROUTER=$!",
        "listening=",
        "for _ in $(seq 300); do",
        "    kill -0 $ROUTER 2>/dev/null || break  # it ended: it could not listen",
        "    (exec 3<>/dev/tcp/127.0.0.1/$PORT) 2>/dev/null && kill -0 $ROUTER 2>/dev/null"
        " && listening=1 && break",
        "    sleep 0.2",
        "done",
        "if [[ -z $listening ]]; then",
        f'    {job_says} the router did not listen on port $PORT; ending the job" >&2',
        "    exit 1",
        "fi",
        "# a counter on every node, its data its own",
        f"srun --overlap --kill-on-bad-exit=1 --nodes={n} --ntasks={n} --ntasks-per-node=1 "
        "--cpus-per-task=1 \\",
        f"    bash -c 'd=$1; shift; id=counter-n$SLURM_NODEID; {counter_user}"
        'exec "$@" --id "$id" --data-dir "$d/$id"\' counter "$DATA" "${MACB[@]}" serve counter &',
        "# one worker slot per task: learner-sK, evaluator-sK, actor-sK (K: the task's rank)",
        f"srun --overlap --kill-on-bad-exit=1 --nodes={n} --ntasks={n * per_node} "
        f"--ntasks-per-node={per_node} --cpus-per-task={job.cpus} \\",
        "    bash -c 'd=$1; shift; id=s$SLURM_PROCID; "
        'exec "$@" --id "$id" --data-dir "$d/slot-$id"\' slot "$DATA" "${MACB[@]}" serve slot '
        f"--actors {job.actors} &",
        f"{user('api')}"
        + (f"MACB_API_GROUP_SIZE={job.group_size} " if job.group_size > 1 else "")
        + f'"${{MACB[@]}}" serve api --id api --listen-http {http}:$API_PORT '
        '--data-dir "$DATA/api" &',
        f'echo "{url}" > "$LOGS/$SLURM_JOB_ID.api"',
        "wait -n",
        'echo "macb cluster job $SLURM_JOB_ID: a part of it ended (exit $?); ending the job" >&2',
        "exit 1",
        "",
    ]
    return "\n".join(lines)


#: How often a failing squeue is asked again before the job's state counts as unknown,
#: and the pause between: a busy or restarting controller answers again within minutes.
SQUEUE_TRIES, SQUEUE_RETRY_S = 6, 10.0


class SlurmUnanswered(RuntimeError):
    """squeue kept failing: where the job stands is unknown (it may well run)."""


def job_state(
    job_id: str,
    run: Runner = run_command,
    tries: int | None = None,
    pause_s: float | None = None,
) -> tuple[str, str] | None:
    """Slurm's state and reason of the job, or None once it no longer knows it (an
    empty listing, or squeue's "Invalid job id specified"). Any other squeue failure
    (the controller busy: "Socket timed out") says nothing about the job: it is asked
    again, `tries` times in all, each said, then SlurmUnanswered."""
    tries, pause_s = tries or SQUEUE_TRIES, SQUEUE_RETRY_S if pause_s is None else pause_s
    why = ""
    for attempt in range(1, tries + 1):
        got = run(["squeue", "-h", "-j", job_id, "-t", "all", "-o", "%T|%r"])
        if not got.returncode:
            if not got.stdout.strip():
                return None
            state, _, reason = got.stdout.strip().splitlines()[0].partition("|")
            return state.strip(), "" if reason.strip() == "None" else reason.strip()
        why = (got.stderr or got.stdout).strip() or f"exit {got.returncode}"
        if "Invalid job id specified" in why:
            return None
        if attempt < tries:
            print(f"cluster job {job_id}: squeue failed ({why}); asking again in "
                  f"{pause_s:.0f} s ({attempt} of {tries})", file=sys.stderr)  # fmt: skip
            time.sleep(pause_s)
    raise SlurmUnanswered(f"squeue failed {tries} times ({why})")


def services_answering(api: ApiClient) -> int | None:
    """How many services answer on the API's /workers (None: the API does not answer
    yet). Raises ApiError when it refuses us (401: our MACB_API_TOKEN is not the job's),
    which waiting does not mend."""
    import httpx

    from services.api.client import ApiError

    try:
        workers = api.workers()["workers"]
    except ApiError as err:
        if err.status in (401, 403):
            raise
        return None
    except (httpx.HTTPError, ValueError, KeyError, TypeError):
        return None
    return sum(1 for w in workers if isinstance(w, dict) and w.get("answers"))


def this_host() -> str:
    """This host's short name, as `hostname -s` gives the job's first node."""
    return socket.gethostname().split(".")[0]


def loopback_elsewhere(url: str, head: str, here: str) -> bool:
    """Whether the job's API at `url` is on the loopback of its first node `head` while
    this command runs on another host `here`: 127.0.0.1 here is not the job's then."""
    host = urlparse(url).hostname or ""
    try:
        loopback = host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:
        loopback = False
    return loopback and head.split(".")[0] != here.split(".")[0]


def how_to_reach(job_id: str, url: str, head: str, log: Path) -> str:
    """What to say when the job's API is on `head`'s loopback, out of this host's reach."""
    port = urlparse(url).port
    return (
        f"cluster job {job_id} runs; its API listens on 127.0.0.1:{port} of {head} (no "
        f"MACB_API_TOKEN: loopback only), which cannot be reached from here, so this command "
        f"does not wait for it (its log: {log}). To use it from here:\n"
        f"  ssh -N -L {port}:127.0.0.1:{port} {head} &        # a tunnel to it, then\n"
        f"  MACB_API_URL=http://127.0.0.1:{port} macb run CONFIG\n"
        f"or submit the cluster with MACB_API_TOKEN=... set: its API then listens on {head}'s "
        "network and wants the token\n"
        f"  scancel {job_id}                         # stop the cluster"
    )


def _read(path: Path) -> str | None:
    try:
        return path.read_text().strip() or None
    except OSError:
        return None


def placement_error(args: argparse.Namespace) -> str | None:
    """Why flags of the local cluster that the job fixes itself cannot be taken, or None:
    the job always runs the API (the command follows it to its API; `macb run` needs it),
    and its router listens where the nodes reach it (loopback on one node, every
    interface on several), so only --endpoint's port is the user's."""
    from cli.supervisor import host_port

    if args.no_api:
        return "--no-api: the job always runs the API on its first node (it is how runs reach it)"
    host, _ = host_port(args.endpoint)
    if host != "127.0.0.1":
        return (
            f"--endpoint {args.endpoint}: the job's router listens on the first node's "
            "loopback (one node) or on every interface (several), so only the port can be "
            "chosen: give tcp/127.0.0.1:PORT"
        )
    return None


def cmd_up_slurm(args: argparse.Namespace) -> int:
    """Write the cluster job's script, submit it and (unless --detach) wait until its API
    answers; say where it is and how to stop it."""
    import os

    from shared.persist.files import default_data_dir
    from shared.settings import settings

    if args.run:
        print("macb up --launcher slurm: submit runs to the job's API (macb run)", file=sys.stderr)
        return 2
    if why := placement_error(args):
        print(f"macb up --launcher slurm: {why}", file=sys.stderr)
        return 2
    secrets = settings().zenoh_secrets
    data_dir = Path(args.data_dir or default_data_dir() / "slurm-cluster").resolve()
    job = ClusterJob(
        nodes=args.nodes,
        slots=args.slots,
        cpus=args.cpus_per_slot,
        actors=args.actors,
        data_dir=data_dir,
        router_port=int(args.endpoint.rsplit(":", 1)[1]),
        api_port=args.api_port,
        secrets=Path(secrets).resolve() if secrets else None,
        api_public=bool(os.environ.get("MACB_API_TOKEN")),
        group_size=args.group_size,
    )
    try:
        extra = tuple(shlex.split(args.sbatch_args or ""))
    except ValueError as err:  # an unclosed quote
        print(f"macb up: --sbatch-args: {err}", file=sys.stderr)
        return 2
    opts = SlurmOptions(args.partition, args.time, args.account, extra)
    if why := job.error():
        print(f"macb up --launcher slurm: {why}", file=sys.stderr)
        return 2
    if why := directive_path_error(
        [
            ("the data folder", job.data_dir, "give --data-dir a folder without it"),
            ("this command's folder", Path.cwd(), "run it from a folder without it"),
        ]
    ):
        print(f"macb up: {why}", file=sys.stderr)
        return 2
    if why := preflight(opts, [data_dir], folder="the data folder", flag="--data-dir"):
        print(f"macb up: {why}", file=sys.stderr)  # it names --launcher slurm or the flag
        return 2
    job.log_dir.mkdir(parents=True, exist_ok=True)
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S")
    script = job.log_dir / f"cluster-{stamp}.sh"
    script.write_text(render_cluster_script(job, macb_argv(), Path.cwd(), opts))
    argv = sbatch_argv(opts, script)
    got = run_command(argv)
    if got.returncode:
        print(f"{shlex.join(argv)} failed: {got.stderr.strip()}", file=sys.stderr)
        return 1
    job_id = parse_job_id(got.stdout)
    log = job.log_dir / f"cluster-{job_id}.log"
    print(
        f"cluster job {job_id} submitted ({job.nodes} node(s) x {job.slots} slot(s)); "
        f"script {script}, log {log}",
        file=sys.stderr,
    )
    if args.detach:
        print(
            f"its API's address will be in {job.log_dir}/{job_id}.api, its first node's "
            f"name in {job_id}.head",
            file=sys.stderr,
        )
        return 0
    return wait_until_up(job_id, job, log, args.wait)


def wait_until_up(
    job_id: str,
    job: ClusterJob,
    log: Path,
    timeout: float,
    run: Runner = run_command,
    here: str | None = None,
) -> int:
    """Follow the job until its API and every service answer (0), or until it ends, its
    API refuses our token or `timeout` passes (1: a job still running is named, with how
    to cancel it). An API on the loopback of a first node that is not this host (`here`)
    is not polled: what to do instead is said, and 0 returned."""
    from services.api.client import ApiClient, ApiError

    here = here or this_host()
    said: list[object] = [None, None]  # the last state and count of services told
    deadline = time.monotonic() + timeout
    url_file, head_file = (job.log_dir / f"{job_id}.{x}" for x in ("api", "head"))
    api: ApiClient | None = None
    try:
        while time.monotonic() < deadline:
            try:
                state = job_state(job_id, run)
            except SlurmUnanswered as err:
                print(
                    f"cluster job {job_id}: where it stands is unknown: {err}. It may well "
                    f"run: `squeue -j {job_id}` says once Slurm answers, `scancel {job_id}` "
                    f"stops it; its log: {log}",
                    file=sys.stderr,
                )
                return 1
            if state is None or state[0] not in ("PENDING", "CONFIGURING", "RUNNING"):
                print(f"cluster job {job_id} ended ({state[0] if state else 'gone'})",
                      file=sys.stderr)  # fmt: skip
                if log.exists():
                    print("\n".join(log.read_text().splitlines()[-20:]), file=sys.stderr)
                return 1
            if state != said[0]:
                said[0] = state
                print(f"cluster job {job_id}: {' '.join(w for w in state if w)}", file=sys.stderr)
            url, head = _read(url_file), _read(head_file)
            if url and head and loopback_elsewhere(url, head, here):
                print(how_to_reach(job_id, url, head, log), file=sys.stderr)
                return 0
            if url and api is None:
                api = ApiClient(url, timeout=3)  # with MACB_API_TOKEN, if set
            try:
                answering = services_answering(api) if api else None
            except ApiError as err:
                print(
                    f"cluster job {job_id}: its API at {url} refuses this command ({err}): "
                    "MACB_API_TOKEN here is not the one the job was submitted with. The job "
                    f"is still running: `scancel {job_id}` stops it",
                    file=sys.stderr,
                )
                return 1
            if answering is not None and answering != said[1]:
                said[1] = answering
                print(f"cluster job {job_id}: {answering} of {job.services} services answer",
                      file=sys.stderr)  # fmt: skip
            if url and answering is not None and answering >= job.services:
                token = ", MACB_API_TOKEN set as here" if job.api_public else ""
                print(
                    f"cluster job {job_id} up: API {url} (dashboard {url}/)\n"
                    f"  MACB_API_URL={url} macb run CONFIG     # experiments, spread over "
                    f"the slots{token}\n"
                    f"  scancel {job_id}                         # stop the cluster",
                    file=sys.stderr,
                )
                print(url)
                return 0
            time.sleep(2)
    finally:
        if api is not None:
            api.close()
    seen = f", last seen {' '.join(w for w in said[0] if w)}," if isinstance(said[0], tuple) else ""
    print(
        f"cluster job {job_id}: not up within {timeout:.0f} s. The job is left as it is{seen} "
        f"and runs until its time limit: `scancel {job_id}` stops it; its log: {log}",
        file=sys.stderr,
    )
    return 1
