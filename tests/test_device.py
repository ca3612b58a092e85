"""The learner's torch device (`device` in the config): the engine builds, updates and
acts on it, checkpoints load anywhere, and a device this machine lacks is refused with
the reason before anything runs. Only the CPU is here to run on; a GPU user's path is
the same code with another device, and torch's `meta` device (shapes, no data) shows
that path reads nothing back from its device inside `update` and `act`."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_leaves

from shared.config import ConfigError, make_config
from shared.core.learners import BatchedMADDPG, LearnerSpec, TunedMADDPG
from shared.core.learners.base import Losses
from shared.core.learners.group import GroupMADDPG
from shared.core.learners.layers import (
    Stack,
    linear_forward,
    linear_grad_input,
    linear_grad_weight,
    relu_,
    relu_backward,
)
from shared.core.learners.precision import DeviceError, device_count, resolve_device
from shared.envs.tasks import task_spec
from shared.run.factories import build_learner
from tests.harness import macb
from tests.test_group_learner import agents_of, assert_same_state, batch


def test_config_takes_device_names_and_refuses_others():
    assert make_config({"task": "simple", "algo": "ddpg"}).device == "cpu"
    assert make_config({"task": "simple", "algo": "ddpg", "device": "cuda:1"}).device == "cuda:1"
    with pytest.raises(ConfigError, match="device"):
        make_config({"task": "simple", "algo": "ddpg", "device": "gpu0"})
    with pytest.raises(ConfigError, match="device cuda needs learner_impl batched"):
        make_config({"task": "simple", "algo": "ddpg", "device": "cuda",
                     "learner_impl": "reference"})  # fmt: skip


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_a_missing_device_is_refused_with_the_reason(tmp_path):
    with pytest.raises(DeviceError, match="device cuda: not available here"):
        resolve_device("cuda")
    with pytest.raises(DeviceError):
        BatchedMADDPG(agents_of("simple"), LearnerSpec(algo="ddpg"), device="cuda")
    out = tmp_path / "o"
    got = macb("train", "--task", "simple", "--algo", "ddpg", "--device", "cuda",
               "--episodes", "1", "--out", str(out), timeout=120)  # fmt: skip
    assert got.returncode == 2 and "device cuda: not available here" in got.stderr
    # Refused before the run's folder is made (it held a .lock and cuts/ before).
    assert not out.exists()


def test_an_explicit_device_runs_the_same_update():
    """device='cpu' given explicitly (a torch.device too) is the default's update."""
    agents = agents_of("speaker_listener")
    specs = [LearnerSpec(algo="cen-maddpg", hidden=(32, 32), seed=s) for s in (0, 1)]
    a = GroupMADDPG(agents, specs)
    b = GroupMADDPG(agents, specs, device=torch.device("cpu"))
    rng = np.random.default_rng(0)
    bs = [batch(rng, agents, 8, True) for _ in specs]
    for g in (a, b):
        g.update(*(np.stack(c) for c in zip(*bs)))
    for r in range(2):
        state = b.run_state_dict(r)
        assert all(t.device.type == "cpu" for t in state["actors"][0].values())
        assert_same_state(a.run_state_dict(r), state, f"run {r}")


# ---------------------------------------------------------------------------------------
# Device-clean: no host read in `update` and `act`, checked on torch's `meta` device,
# whose tensors have shapes and no data (any read of a value, `.item()`, `.tolist()`,
# `.cpu()`, `float(t)`, `if t:`, raises there), with a dispatch mode that sees every
# op's tensor arguments.
META_CASES = [
    ("speaker_listener", "cen-maddpg"),
    ("spread", "dis-maddpg"),
    ("simple", "ddpg"),
]


class OpLog(TorchDispatchMode):
    """Every op under it, with its tensor arguments not on `device`."""

    def __init__(self, device: str) -> None:
        super().__init__()
        self.device = device
        self.ops: list[str] = []
        self.off: list[tuple[str, bool | None]] = []  # (op, non_blocking) of off-device args

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # noqa: ANN001
        kwargs = kwargs or {}
        self.ops.append(str(func))
        if any(
            isinstance(t, torch.Tensor) and t.device.type != self.device
            for t in tree_leaves((args, kwargs))
        ):
            self.off.append((str(func), kwargs.get("non_blocking")))
        return func(*args, **kwargs)

    def copies_in(self) -> int:
        """Host-to-device copies: each must be non-blocking, and nothing else may read
        a host tensor (`detach` is the staging buffer's numpy view)."""
        copies = 0
        for op, non_blocking in self.off:
            if op == "aten._to_copy.default":
                assert non_blocking is True, "a blocking host-to-device copy"
                copies += 1
            else:
                assert op == "aten.detach.default", f"{op} reads a tensor off the device"
        return copies


def meta_group(task: str, algo: str, precision: str, runs: int = 12) -> GroupMADDPG:
    specs = [LearnerSpec(algo=algo, hidden=(64, 48), seed=s) for s in range(runs)]
    return GroupMADDPG(agents_of(task), specs, precision=precision, device="meta")


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
@pytest.mark.parametrize("per_agent", [False, True], ids=["per-run", "per-agent"])
@pytest.mark.parametrize("task,algo", META_CASES)
def test_a_12_run_group_updates_and_acts_on_meta_without_host_reads(
    task, algo, per_agent, precision
):
    """The fig8-sized group's update and act run on `meta`: nothing reads a device
    value on the host, the inputs of a step go in one non-blocking copy, and every
    other op reads tensors on the device only. The losses stay on it, unread."""
    g = meta_group(task, algo, precision)
    agents = agents_of(task)
    rng = np.random.default_rng(0)
    for _ in range(2):  # the first update creates Adam's state, the second uses it
        bs = [batch(rng, agents, 16, per_agent) for _ in range(g.runs)]
        with OpLog("meta") as log:
            losses = g.update(*(np.stack(c) for c in zip(*bs)))
        assert log.copies_in() == 1
        assert "aten._fused_adam_.default" in log.ops
    assert isinstance(losses, Losses) and losses.tensor.device.type == "meta"
    with pytest.raises((NotImplementedError, RuntimeError)):  # no data: never read
        losses["critic_loss"]
    obs = rng.standard_normal((g.runs, 5, g.joint_obs)).astype(np.float32)
    with OpLog("meta") as log:
        actions = g.act_on_device(obs)
    assert log.copies_in() == 1
    assert actions.device.type == "meta" and actions.shape == (g.runs, 5, g.joint_act)
    with pytest.raises((NotImplementedError, RuntimeError)):  # `act` reads its actions
        g.act(obs)


def test_a_run_alone_updates_and_acts_on_meta_without_host_reads():
    """The batched learner alone: the same (lanes asked for fall back to one)."""
    agents = agents_of("speaker_listener")
    m = BatchedMADDPG(agents, LearnerSpec(algo="cen-maddpg", hidden=(32, 32)), lanes=2,
                      device="meta")  # fmt: skip
    assert m.lanes.n == 1
    rng = np.random.default_rng(0)
    with OpLog("meta") as log:
        m.update(*batch(rng, agents, 16, False))
        m.act_on_device(rng.standard_normal((3, m.joint_obs)).astype(np.float32))
    assert log.copies_in() == 2  # one per call


def all_tensors(g: GroupMADDPG) -> dict[str, torch.Tensor]:
    """Every tensor the learner holds, by where: its attributes, its stacks (but their
    `index`, the host's map of the per-agent checkpoint layout) and its optimizers'
    state."""
    found: dict[str, torch.Tensor] = {}

    def walk(x, path: str) -> None:
        if isinstance(x, torch.Tensor):
            found[path] = x
        elif isinstance(x, dict):
            for k, v in x.items():
                walk(v, f"{path}[{k if not isinstance(k, torch.Tensor) else 'p'}]")
        elif isinstance(x, list | tuple):
            for i, v in enumerate(x):
                walk(v, f"{path}[{i}]")
        elif isinstance(x, Stack):
            for k, v in vars(x).items():
                if k != "index":
                    walk(v, f"{path}.{k}")
        elif isinstance(x, torch.optim.Optimizer):
            walk(list(x.state.values()), f"{path}.state")

    for k, v in vars(g).items():
        walk(v, k)
    return found


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_a_group_built_for_a_device_holds_everything_there(precision):
    """Built on the CPU and moved once: every weight, target, constant, bf16 copy and
    Adam state of a group made for `meta` is on `meta` (a group that copied anything
    back to the CPU while building would fail: meta has no data to copy)."""
    g = meta_group("speaker_listener", "cen-maddpg", precision, runs=3)
    rng = np.random.default_rng(0)
    bs = [batch(rng, agents_of("speaker_listener"), 8, False) for _ in range(3)]
    g.update(*(np.stack(c) for c in zip(*bs)))
    held = all_tensors(g)
    assert any("optim.state" in k for k in held)
    assert any(k.startswith("_low") for k in held) == (precision == "bf16")  # bf16's copies
    assert {k for k, t in held.items() if t.device.type != "meta"} == set()


def test_cpu_only_mechanisms_stay_on_the_cpu(monkeypatch):
    """Subnormal flushing (a CPU mode), the per-run parts of the elementwise passes, the
    lanes and the tuner's thread switching run on the CPU and nowhere else."""
    flushes: list[bool] = []
    monkeypatch.setattr(torch, "set_flush_denormal", lambda on: flushes.append(on) or True)
    agents = agents_of("speaker_listener")
    specs = [LearnerSpec(algo="cen-maddpg", hidden=(32, 24), seed=s) for s in range(3)]
    on_cpu, on_meta = GroupMADDPG(agents, specs), GroupMADDPG(agents, specs, device="meta")
    rng = np.random.default_rng(0)
    bs = [batch(rng, agents, 8, False) for _ in specs]
    on_meta.update(*(np.stack(c) for c in zip(*bs)))
    assert flushes == []
    on_cpu.update(*(np.stack(c) for c in zip(*bs)))
    assert flushes == [True, False]
    params = on_cpu.actor.params
    assert len(on_cpu._parts(params)) > len(params)  # some go run by run on the CPU
    assert len(on_meta._parts(on_meta.actor.params)) == len(params)  # whole elsewhere
    cfg = make_config({"task": "speaker_listener", "algo": "cen-maddpg", "hidden": [32, 24]})
    assert isinstance(build_learner(cfg, task_spec("speaker_listener")), TunedMADDPG)
    on_device = build_learner(cfg.model_copy(update={"device": "meta"}),
                              task_spec("speaker_listener"))  # fmt: skip
    assert isinstance(on_device, BatchedMADDPG) and on_device.lanes.n == 1


def ops_of(fn, *args) -> list[str]:
    with OpLog("none") as log:
        fn(*args)
    return log.ops


def test_layer_tricks_are_the_cpus_only():
    """The CPU's layout copies, its stack of two for a one-output network and bf16's
    int16 ReLU: taken on the CPU, the plain ops on another device."""
    for device in ("cpu", "meta"):
        cpu = device == "cpu"
        narrow_x, grad = torch.zeros(2, 8, 3, device=device), torch.zeros(2, 8, 16, device=device)
        assert ("aten.clone.default" in ops_of(linear_grad_weight, grad, narrow_x)) == cpu
        w = torch.zeros(2, 16, 3, device=device)
        assert (ops_of(linear_grad_input, grad, w).count("aten.transpose.int") > 1) == cpu
        one = [torch.zeros(1, 1, 4, device=device), torch.zeros(1, 1, 1, device=device)]
        x = torch.zeros(1, 8, 4, device=device)
        assert ("aten.expand.default" in ops_of(linear_forward, x, *one)) == cpu
        h = torch.zeros(2, 4, device=device, dtype=torch.bfloat16)
        assert ("aten.view.dtype" in ops_of(relu_, h)) == cpu
        assert ("aten.view.dtype" in ops_of(relu_backward, h, h)) == cpu


def test_losses_are_read_when_read_and_equal_an_eager_read():
    """On the CPU the losses a caller reads are the update's, as floats."""
    agents = agents_of("speaker_listener")
    m = BatchedMADDPG(agents, LearnerSpec(algo="cen-maddpg", hidden=(32, 32)))
    losses = m.update(*batch(np.random.default_rng(0), agents, 16, False))
    assert repr(losses) == "Losses(unread)"
    assert dict(losses) == dict(zip(Losses.KEYS, losses.tensor.tolist()))
    assert all(isinstance(v, float) for v in losses.values()) and losses["actor_loss"] != 0


def test_device_count_spreads_a_bare_gpu_name_only():
    assert device_count("cpu") == 0
    assert device_count("cuda:1") == 1
    assert device_count("cuda") == (torch.cuda.device_count() if torch.cuda.is_available() else 0)


def test_reproduce_takes_a_device_for_every_run(tmp_path):
    """`macb reproduce --device`: every run's config, the experiment's name and its
    default folder say the device; a name torch does not know, or a device this
    machine lacks, is refused with the reason before any run starts."""
    import argparse

    from cli.reproduce.command import figure_body, out_name
    from cli.reproduce.figures import FIGURES

    fig = FIGURES["fig3"]
    args = argparse.Namespace(
        seeds=[0], profile="mpe2", episodes=2, precision=None, arms=None, threads=None,
        local=True, report_only=False, status=False, device="cuda:1",
    )  # fmt: skip
    body = figure_body(fig, args)
    assert body["device"] == "cuda:1" and "device=cuda:1" in body["name"]
    assert out_name(fig, args) == "fig3-mpe2-cuda1"
    args.device = "cpu"
    assert "device" not in figure_body(fig, args) and out_name(fig, args) == "fig3-mpe2"
    base = ("reproduce", "fig3", "--local", "--seeds", "0", "--episodes", "2", "--arms",
            "beta=0.0", "--quiet", "--out", str(tmp_path))  # fmt: skip
    bad = macb(*base, "--device", "gpu0", timeout=120)
    assert bad.returncode == 2 and "device" in bad.stderr and not (tmp_path / "runs").exists()
    if not torch.cuda.is_available():
        got = macb(*base, "--device", "cuda", timeout=300)
        assert got.returncode == 2 and "device cuda: not available here" in got.stderr
        assert "nothing was run" in got.stderr and not (tmp_path / "runs").exists()
        # and nothing after it: no "trained in", no page refused for want of runs
        assert "trained in" not in got.stderr and "has a folder" not in got.stderr, got.stderr


@pytest.mark.parametrize("profile", ["mpe2", "thesis"], ids=["per-run", "per-agent"])
def test_a_12_run_groups_replay_lives_on_meta_and_its_step_reads_nothing_back(profile):
    """The group's step with its replay on the device (`GroupReplay`'s torch backend),
    on `meta`: acting, a collection step's rows (one non-blocking copy for the group),
    the draws (on the host, each run's sampler) and their bonuses (priced on the host)
    sent in one copy and gathered there, and the update on those tensors (no copy at
    all) read no device value back; every replay field is a `meta` tensor."""
    from cli.trainer import GroupRun
    from tests.test_pricing import ARMS

    arms = [{**arm, "seed": s} for s in range(2) for arm in ARMS]
    cfgs = [
        make_config({"task": "speaker_listener", "algo": "cen-maddpg", "episodes": 50,
                     "hidden": [16, 16], "profile": profile, "learning_starts": 0,
                     "warmup": "policy", **arm}).model_copy(update={"device": "meta"})
        for arm in arms
    ]  # fmt: skip
    g = GroupRun(cfgs, [None] * len(cfgs), 60.0)
    assert g.runs == 12 and g.replay.backend == "torch"
    assert {t.device.type for t in g.replay.tensors.values()} == {"meta"}
    live = [r != 3 for r in range(g.runs)]  # run 3 stopped by its rule: its fixed draw
    k = g.minibatches_per_update
    acted: list[int] = []

    def policy(obs: np.ndarray) -> np.ndarray:
        with OpLog("meta") as log:
            g.learner.act_on_device(obs)
        assert log.copies_in() == 1
        acted.append(len(obs))
        return np.zeros((*obs.shape[:-1], g.learner.joint_act), np.float32)

    for _ in range(3):
        tr = g.collector.step(policy)
        for r, m in enumerate(g.members):
            m.collect(tr.obs[r], tr.act[r], float(tr.rew[r]), tr.next_obs[r],
                      float(tr.done[r]), int(tr.collisions[r]))  # fmt: skip
        with OpLog("meta") as log:
            g.replay.flush()
        assert log.copies_in() == 1 and not g.replay.pending
        rngs = [m.sample_rng if on else None for m, on in zip(g.members, live)]
        idx = g.replay.draw(g.cfg.batch_size, k, rngs)
        bonuses = [m.price(idx[r]) if live[r] else None for r, m in enumerate(g.members)]
        with OpLog("meta") as log:
            arrays = g.update_arrays(idx, bonuses, live)
        assert log.copies_in() == 1
        assert "aten.index_select.default" in log.ops
        assert all(a.device.type == "meta" for a in arrays)
        with OpLog("meta") as log:
            g.learner.update(*arrays)
        assert log.copies_in() == 0  # its inputs are on the device already
    assert acted == [g.runs] * 3
