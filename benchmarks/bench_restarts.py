"""What restarting a few envs costs a training batch: the env's reset of ``--flagged`` envs of ``--batch``
(TorchRL's partial reset, as the collector calls it for the envs that ended), with their start states taken from
the env's pool (``_pooled_starts``, what ``_reset`` does) against drawn on the spot (``_initial_state``: the
kinematics of ``--flagged`` start states).

    python benchmarks/bench_restarts.py                       # ant, 2048 envs, 4 flagged (a main-job step's typical count)

Milliseconds per call, medians of ``--repeats`` timings of at least 0.5 s each, float32, CPU, every thread.
"""

import argparse

import torch
from tensordict import TensorDict

import torchsim.envs
from _timing import median_rate


def ms_per_call(fn, repeats: int) -> float:
    for _ in range(20):  # warm-up: the first calls allocate and fill the pool
        fn()
    return 1e3 / median_rate(fn, 1, repeats)


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env", default="ant")
    p.add_argument("--batch", type=int, default=2048)
    p.add_argument("--flagged", type=int, default=4)
    p.add_argument("--repeats", type=int, default=5)
    args = p.parse_args()
    env = torchsim.envs.make(args.env, num_envs=args.batch, stepper="auto")
    flagged = torch.zeros(args.batch, 1, dtype=torch.bool)
    flagged[torch.randperm(args.batch)[:args.flagged]] = True
    partial = TensorDict(_reset=flagged, batch_size=[args.batch])
    pooled = ms_per_call(lambda: env._pooled_starts(args.flagged), args.repeats)
    drawn = ms_per_call(lambda: env._initial_state(args.flagged), args.repeats)
    reset = ms_per_call(lambda: env._reset(partial), args.repeats)
    env._pooled_starts = env._initial_state  # the reset as it ran before the pool
    reset_drawn = ms_per_call(lambda: env._reset(partial), args.repeats)
    print(f"{args.env}, {args.batch} envs, {args.flagged} flagged, {torch.get_num_threads()} threads, ms per call:\n"
          f"| start states from the pool | drawn on the spot | env._reset (pooled) | env._reset, drawn on the spot |\n"
          f"|---|---|---|---|\n| {pooled:.3f} | {drawn:.3f} | {reset:.3f} | {reset_drawn:.3f} |")


if __name__ == "__main__":
    main()
