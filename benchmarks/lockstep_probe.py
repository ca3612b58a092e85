"""Lockstep over the bus: central inference or weights shipped every step?

`interleave: lockstep` needs each step's action to come from the weights after the last
step's update. Two designs: the learner computes the action (central inference, SEED
RL's: an observation goes to the learner, an action comes back), or the learner ships
its actors' weights after every update and the actor loads them. This times what each
costs per environment step in one process, the bus's transport left out (it only adds
to the larger message): for central inference the learner's `act` on one observation
plus encoding and decoding `act_request` and `action`; for weights every step encoding
the `weights` message of the actors, decoding it and loading it into the actor's
`JointPolicy`. Alternating A B A B, `--rounds` rounds of `--calls` calls each; the
ratio is taken per round. The workload is the thesis's speaker_listener Cen-MADDPG with
hidden 400-300 (bench_e2e's).

    .venv/bin/python benchmarks/lockstep_probe.py [--rounds 4] [--calls 200]

prints the CPU, a markdown table and the median ratio.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch
from _stats import cpu_model  # (benchmarks/ is the script's folder)

from shared.config import make_config
from shared.core.networks import JointPolicy, weights_as_arrays
from shared.envs.tasks import task_spec_for
from shared.net.messages import Action, ActRequest, Weights
from shared.net.wire import decode, encode
from shared.run.factories import build_learner


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--calls", type=int, default=200)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    cfg = make_config(
        {
            "task": "speaker_listener",
            "algo": "cen-maddpg",
            "explore": "cen-macb",
            "hidden": [400, 300],
            "learner_lanes": 1,
        }
    )
    spec = task_spec_for(cfg)
    learner = build_learner(cfg, spec)
    policy = JointPolicy.for_task(spec, cfg.hidden)
    obs = np.zeros((1, spec.joint_obs_dim), np.float32)

    def weights_every_step() -> int:
        payload = encode(
            Weights(
                "run",
                version=1,
                updates=1,
                env_steps=1,
                episodes=1,
                eval_point=-1,
                collisions_cum=0,
                actors=weights_as_arrays(learner.actor_weights()),
                stats={},
                incarnation="probe",
            )
        )
        msg = decode(payload, Weights)
        policy.load([{k: np.array(v) for k, v in sd.items()} for sd in msg.actors])
        return len(payload)

    def central_inference() -> int:
        ask = encode(ActRequest("run", actor="actor0", seq=1, obs=obs[0]))
        got = decode(ask, ActRequest).obs
        act = learner.act(np.array(got)[None])[0].astype(np.float32)
        answer = encode(Action("run", seq=1, act=act))
        decode(answer, Action)
        return len(ask) + len(answer)

    cases = {"central inference": central_inference, "weights every step": weights_every_step}
    size = {name: fn() for name, fn in cases.items()}
    times: dict[str, list[float]] = {name: [] for name in cases}
    for _ in range(args.rounds):
        for name, fn in cases.items():  # A B A B
            t0 = time.perf_counter()
            for _ in range(args.calls):
                fn()
            times[name].append(1e3 * (time.perf_counter() - t0) / args.calls)
    print(f"CPU: {cpu_model()}; one torch thread; {args.rounds} rounds x {args.calls} calls\n")
    print("| design | ms per step (median) | bytes on the bus per step |")
    print("|---|---|---|")
    for name in cases:
        print(f"| {name} | {statistics.median(times[name]):.3f} | {size[name]:,} |")
    ratios = [w / c for w, c in zip(times["weights every step"], times["central inference"])]
    print(f"\nweights every step / central inference: {statistics.median(ratios):.1f}x (median)")


if __name__ == "__main__":
    main()
