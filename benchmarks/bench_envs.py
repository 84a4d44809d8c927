"""Env-steps/s of every torchsim env next to MuJoCo C stepping the same MJCF with the same frame count.

    python benchmarks/bench_envs.py                                   # all envs, batches 1 256 4096, compiled
    python benchmarks/bench_envs.py --envs ant hopper --batches 256 --modes eager compiled --out /tmp/envs.md

torchsim: ``env.step`` on a TensorDict of random actions in [-1, 1] (the path TorchRL takes), ``num_envs=batch``,
float32, CPU. "compiled" = ``torch.compile(fullgraph=True)`` of the physics substep (the substep loop, frame loop
and the env's observation/reward code stay eager; compiling whole env steps unrolls frame_skip x substeps copies
of the substep into one graph, which does not finish compiling in reasonable time on 2 cores). The first compiled
call (trace + compile) is reported as the compile time. MuJoCo C: ``mujoco.rollout`` on the same MJCF, the same
batch, ``frame_skip`` physics steps per env step, random controls held over each env step, one thread per core.
Each number is the median of ``--repeats`` timings; the ratio is torchsim / MuJoCo from the same run.
"""

import argparse
import os
import statistics
import time

import mujoco
import numpy as np
import torch
from tensordict import TensorDict

import torchsim
import torchsim.envs
from _timing import allow_recompiles, emit_table, mujoco_rollout_rate, mujoco_start_states


def parse_args():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--envs", nargs="+", default=torchsim.envs.list("physics"), choices=torchsim.envs.list("physics"))
    p.add_argument("--batches", nargs="+", type=int, default=[1, 256, 4096])
    p.add_argument("--modes", nargs="+", default=["compiled"], choices=["eager", "compiled"])
    p.add_argument("--steps", type=int, default=5, help="timed env steps per repeat")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: one per core)")
    p.add_argument("--out", default=None, help="also write the table as markdown here")
    return p.parse_args()


def log(msg):
    print(msg, flush=True)


def time_torchsim(env, steps: int, repeats: int) -> float:
    td = TensorDict(action=env.action_spec.rand(), batch_size=env.batch_size)
    env.step(td)  # warm-up (compiled: already compiled by the caller)
    rates = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(steps):
            td["action"] = env.action_spec.rand()
            env.step(td)
        rates.append(env.batch_size[0] * steps / (time.perf_counter() - start))
    return statistics.median(rates)


def time_mujoco(env, batch: int, steps: int, repeats: int) -> float:
    m = env.mj_model
    q, qd = (x.double().numpy() for x in env._sample_init(batch))
    lo, hi = m.actuator_ctrlrange[:, 0], m.actuator_ctrlrange[:, 1]
    ctrl = np.random.default_rng(0).uniform(lo, hi, (batch, steps, m.nu)).repeat(env.frame_skip, axis=1)
    threads = os.cpu_count() or 1
    return mujoco_rollout_rate(m, mujoco_start_states(m, q, qd), ctrl, repeats, threads) / env.frame_skip


def main():
    args = parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    allow_recompiles()
    log(f"torch {torch.__version__}, mujoco {mujoco.__version__}, {torch.get_num_threads()} torch threads, "
        f"{os.cpu_count()} cores; float32 CPU; {args.steps} env steps x {args.repeats} repeats (median)")
    rows = []
    for name in args.envs:
        torch._dynamo.reset()  # each env compiles its own graphs
        for batch in args.batches:
            env = torchsim.envs.make(name, num_envs=batch)
            env.reset()
            row = {"env": name, "batch": batch, "frame_skip": env.frame_skip, "substeps": env.sys.substeps,
                   "dt": env.dt}
            for mode in args.modes:
                env.stepper = torchsim.Stepper(env.base_sys, "auto" if mode == "compiled" else "eager")
                if mode == "compiled":
                    start = time.perf_counter()
                    env.step(TensorDict(action=env.action_spec.rand(), batch_size=env.batch_size))
                    row["compile_s"] = time.perf_counter() - start
                row[mode] = time_torchsim(env, args.steps, args.repeats)
                log(f"{name:>25} batch {batch:>5} {mode:>8}: {row[mode]:>10,.0f} env-steps/s"
                    + (f" (compile {row['compile_s']:.0f} s)" if mode == "compiled" else ""))
            row["mujoco"] = time_mujoco(env, batch, args.steps, args.repeats)
            log(f"{name:>25} batch {batch:>5}   MuJoCo: {row['mujoco']:>10,.0f} env-steps/s")
            rows.append(row)
    header = ("| env | batch | frames x substeps | " + " | ".join(f"torchsim {m}" for m in args.modes)
              + " | MuJoCo C | " + " | ".join(f"{m} / MuJoCo" for m in args.modes) + " |")
    lines = [header, "|" + "---|" * (header.count("|") - 1)]
    for r in rows:
        lines.append(f"| {r['env']} | {r['batch']} | {r['frame_skip']} x {r['substeps']} | "
                     + " | ".join(f"{r[m]:,.0f}" for m in args.modes) + f" | {r['mujoco']:,.0f} | "
                     + " | ".join(f"{r[m] / r['mujoco']:.3g}" for m in args.modes) + " |")
    emit_table("\n".join(lines), args.out, log)


if __name__ == "__main__":
    main()
