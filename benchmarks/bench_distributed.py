"""Data-parallel PPO throughput, one rank against two (``torchrun``, gloo), side by side in one run:

    python benchmarks/bench_distributed.py                    # the main job's settings (PPO on Ant)
    python benchmarks/bench_distributed.py env=halfcheetah --iterations 20

Runs, one after the other, each timing ``--iterations`` PPO iterations (collector + update + the ranks' moment
averaging) after ``--warmup`` iterations that compile:
1. one process, one thread, ``num_envs / 2`` envs (what one rank of run 2 simulates);
2. ``torchrun --nproc_per_node=2``, one thread per rank, ``num_envs`` envs in all (``num_envs / 2`` each);
3. one process, two threads, ``num_envs`` envs (the main job as ``python -m torchsim.train`` runs it).
Each rank also times the gradient all-reduce alone (``Ranks.average_grads_`` on the PPO loss's parameters, the
median of 200). Env steps count every rank's. ``key=value`` arguments are config overrides, as for
``python -m torchsim.train``; ``num_envs`` is ``algo.num_envs`` (default: the main job's 2048).
"""

import argparse
import os
import subprocess
import sys
import time

import numpy as np
import torch
from hydra import compose, initialize_config_dir

from torchsim.algos.distributed import Ranks
from torchsim.algos.ppo import PPO
from torchsim.algos.train import CONFIG_DIR, prepare


def worker(overrides: list[str], iterations: int, warmup: int) -> None:
    """One rank (or the only process): time PPO iterations; rank 0 prints one ``RESULT`` line."""
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose(config_name="config", overrides=overrides)
    ranks = Ranks.from_env(cfg.device)
    prepare(cfg, ranks)
    ppo = PPO(cfg, ranks)
    batches = iter(ppo.collector)
    norm = ppo.env.transform[0]

    def iteration():
        ppo.update(next(batches), lambda *args: None)
        ranks.average_moments_(norm)

    for _ in range(warmup):
        iteration()
    ranks.agree(True)  # start the clock together
    start = time.perf_counter()
    for _ in range(iterations):
        iteration()
    seconds = time.perf_counter() - start
    params = list(ppo.loss_module.parameters())
    for p in params:
        p.grad = torch.randn_like(p)
    times = []
    for _ in range(200):
        t = time.perf_counter()
        ranks.average_grads_(params)
        times.append(time.perf_counter() - t)
    if ranks.is_main:
        frames = ranks.shard(cfg.algo.num_envs) * cfg.algo.unroll * ranks.world_size * iterations
        count = sum(p.numel() for p in params)
        print(f"RESULT {frames / seconds:.0f} {seconds / iterations * 1e3:.1f} {np.median(times) * 1e6:.0f} {count}",
              flush=True)
    ppo.collector.shutdown()
    ranks.close()


def launch(cmd: list[str]) -> list[str]:
    print("$", " ".join(cmd), flush=True)
    proc = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT")]
    if proc.returncode or not lines:
        raise SystemExit(f"failed ({proc.returncode}):\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}")
    return lines[0].split()[1:]


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("overrides", nargs="*")
    p.add_argument("--iterations", type=int, default=30)
    p.add_argument("--warmup", type=int, default=3)
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.worker:
        return worker(args.overrides, args.iterations, args.warmup)
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        num_envs = compose(config_name="config", overrides=args.overrides).algo.num_envs
    me = [os.path.abspath(__file__), "--worker", f"--iterations={args.iterations}", f"--warmup={args.warmup}"]
    keep = [o for o in args.overrides if not o.startswith(("threads=", "algo.num_envs="))]
    runs = [("1 process, 1 thread", num_envs // 2, [sys.executable, *me, "threads=1"]),
            ("torchrun, 2 ranks x 1 thread", num_envs, ["torchrun", "--nproc_per_node=2", "--master_port=29533", *me,
                                                        "threads=1"]),
            ("1 process, 2 threads", num_envs, [sys.executable, *me, "threads=2"])]
    rows = []
    for name, envs, cmd in runs:
        rate, ms, allreduce_us, count = launch([*cmd, f"algo.num_envs={envs}", *keep])
        rows.append((name, envs, float(rate), float(ms), allreduce_us, count))
    base = rows[0][2]
    print(f"\n{' '.join(keep) or 'main job settings'}; {args.iterations} iterations timed after {args.warmup}")
    print("| run | envs in all | env-steps/s | ms per iteration | of run 1 | gradient all-reduce [us] |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, envs, rate, ms, allreduce_us, count in rows:
        print(f"| {name} | {envs} | {rate:,.0f} | {ms:.0f} | {rate / base:.2f} | {allreduce_us} ({count} params) |")


if __name__ == "__main__":
    main()
