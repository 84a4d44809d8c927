"""Each ``torchsim.Stepper`` strategy against MuJoCo C, per model and batch: the measurements behind
the table ``torchsim.execution.STRATEGIES`` (``docs/execution.md``).

    python benchmarks/bench_strategies.py                                  # ant, humanoid, halfcheetah; 1/64/1024/4096
    python benchmarks/bench_strategies.py --models ant --simdlen 256       # AVX2 code on an AVX-512 machine
    python benchmarks/bench_strategies.py --models ant --batches 1 64 --strategies kernel loop eager
    python benchmarks/bench_strategies.py --models ant:impulse ant:soft --batches 4096 --strategies kernel

Physics steps/s (batch x steps / s, float32, CPU, every thread) of one Stepper per model and strategy, built once and
timed at every batch (its compile, on the first step of each new shape, is reported and not timed), from the env's
reset distribution under random controls; MuJoCo C (``mujoco.rollout``, one thread per core) from the same starts
under the same controls in the same run. Medians of ``--repeats``. Prints a markdown table (``--out`` writes it).
"""

import argparse
import os
import platform
import time

import mujoco
import numpy as np
import torch

import torchsim
import torchsim.envs
from _timing import emit_table, median_rate, mujoco_rollout_rate, mujoco_start_states


def parse_args():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", nargs="+", default=["ant", "humanoid", "halfcheetah"],
                   help="env names, each optionally with a contact model: ant:impulse, ant:soft (default: the task's)")
    p.add_argument("--batches", nargs="+", type=int, default=[1, 64, 1024, 4096])
    p.add_argument("--strategies", nargs="+", default=["kernel", "loop"])
    p.add_argument("--simdlen", type=int, default=None, help="inductor cpp.simdlen (256: AVX2 code); for the "
                   "kernel strategy set ATEN_CPU_CAPABILITY=avx2 instead")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--min-seconds", type=float, default=0.5, help="per repeat")
    p.add_argument("--out", default=None)
    return p.parse_args()


def main():
    args = parse_args()
    options = {"cpp.simdlen": args.simdlen} if args.simdlen else {}
    isa = f"simdlen {args.simdlen}" if args.simdlen else "native SIMD"
    print(f"torch {torch.__version__}, mujoco {mujoco.__version__}, {platform.processor() or platform.machine()}, "
          f"{torch.get_num_threads()} threads, {os.cpu_count()} cores, float32, {isa}", flush=True)
    rows = []
    for name in args.models:
        task, _, contact_model = name.partition(":")
        env = torchsim.envs.make(task, num_envs=1, contact_model=contact_model or None)
        sys, m = env.base_sys, env.mj_model
        rng = np.random.default_rng(0)
        steppers = {s: torchsim.Stepper(sys, s, inductor_options=options) for s in args.strategies}
        for batch in args.batches:
            q, qd = env._sample_init(batch)
            lo, hi = m.actuator_ctrlrange.T
            ctrl_np = rng.uniform(lo, hi, (batch, m.nu))
            ctrl = torch.tensor(ctrl_np, dtype=sys.dtype)
            row = {"model": name, "batch": batch}
            for strategy, stepper in steppers.items():
                state = [torchsim.init(sys, q, qd)]

                def run():
                    state[0] = stepper(state[0], ctrl)

                with torch.no_grad():
                    start = time.perf_counter()
                    run()  # compiles on a new shape (a row graph: once for every batch above one env)
                    first_s = time.perf_counter() - start
                    row[strategy] = median_rate(run, batch, args.repeats, args.min_seconds)
                print(f"{name} batch {batch} {strategy}: {row[strategy]:,.0f} steps/s (first step {first_s:.1f} s)",
                      flush=True)
            nstep = max(1, 20_000 // batch)
            start_states = mujoco_start_states(m, q.double().numpy(), qd.double().numpy())
            row["mujoco"] = mujoco_rollout_rate(m, start_states, np.repeat(ctrl_np[:, None], nstep, 1),
                                                args.repeats, os.cpu_count() or 1)
            print(f"{name} batch {batch} MuJoCo C: {row['mujoco']:,.0f} steps/s", flush=True)
            rows.append(row)
    header = ("| model | batch | " + " | ".join(f"{s} steps/s" for s in args.strategies) + " | MuJoCo C | "
              + " | ".join(f"{s} / MuJoCo" for s in args.strategies) + " |")
    lines = [header, "|" + "---|" * (header.count("|") - 1)]
    for r in rows:
        lines.append(f"| {r['model']} | {r['batch']} | " + " | ".join(f"{r[s]:,.0f}" for s in args.strategies)
                     + f" | {r['mujoco']:,.0f} | " + " | ".join(f"{r[s] / r['mujoco']:.2f}" for s in args.strategies)
                     + " |")
    emit_table("\n".join(lines), args.out)


if __name__ == "__main__":
    main()
