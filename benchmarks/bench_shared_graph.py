"""One compiled step for every batch size: an env compiled at a training batch, then envs of other sizes sharing its
System (as the training recipes' evaluation env does), with what each compiles and its env-steps/s.

    python benchmarks/bench_shared_graph.py                        # Ant: trained at 2048, then 128, 64 and 1 envs
    python benchmarks/bench_shared_graph.py --env halfcheetah --train-batch 1024 --batches 128

Prints the first step's seconds (compiling included) and the dynamo graphs and row graphs it added, then the
median env-steps/s of ``env.step`` under random actions (no grad, as collectors step) at each size. Run it at
another commit (``git worktree``) to compare; the compile cache on disk makes a second run of the same commit load
its graphs instead of compiling them (``TORCHSIM_CACHE_DIR``, ``TORCHINDUCTOR_CACHE_DIR``).
"""

import argparse
import time

import torch

import torchsim.envs
from _timing import median_rate


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env", default="ant")
    p.add_argument("--train-batch", type=int, default=2048)
    p.add_argument("--batches", type=int, nargs="+", default=[128, 64, 1])
    p.add_argument("--repeats", type=int, default=5)
    args = p.parse_args()
    graphs = torch._dynamo.utils.counters["stats"]

    def first_step(env):
        before, start = graphs["unique_graphs"], time.perf_counter()
        with torch.no_grad():
            env.rand_step(env.reset())
        print(f"batch {env.batch_size[0]}: first step {time.perf_counter() - start:.1f} s, "
              f"{graphs['unique_graphs'] - before} new dynamo graphs, {env.stepper.num_kernels} step kernels in all",
              flush=True)

    def rate(env):
        td = env.reset()
        td["action"] = env.action_spec.rand()
        with torch.no_grad():
            return median_rate(lambda: env.step(td), env.batch_size[0], args.repeats)

    train = torchsim.envs.make(args.env, num_envs=args.train_batch, stepper="auto")
    first_step(train)
    others = [torchsim.envs.make(args.env, num_envs=b, stepper=train.stepper) for b in args.batches]
    for env in others:
        first_step(env)
    for env in [train, *others]:
        print(f"batch {env.batch_size[0]}: {rate(env):,.0f} env-steps/s", flush=True)


if __name__ == "__main__":
    main()
