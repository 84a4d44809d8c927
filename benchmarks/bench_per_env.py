"""Per-env physics parameters (domain randomisation) against shared ones, side by side.

    python benchmarks/bench_per_env.py                          # ant, humanoid, halfcheetah at 64, 1024 and 4096 envs

Physics steps/s (batch x steps / s, float32, CPU, every thread) of the env's default Stepper (``stepper="auto"``) on
the env's System as it ships, and on the same System after ``set_physics`` draws a mass, friction and actuator-gain
scale per env (uniform in [0.8, 1.2]): the same starts and random controls, the two taking turns in each of
``--repeats`` repeats (rates: medians of the repeats; the ratio: the median of the repeats' ratios).
Each stepper's build (its first step) is reported and not timed.
"""

import argparse
import statistics
import time

import torch

import torchsim
import torchsim.envs
from _timing import alternating_rates, emit_table


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", nargs="+", default=["ant", "humanoid", "halfcheetah"])
    p.add_argument("--batches", nargs="+", type=int, default=[64, 1024, 4096])
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--out", default=None)
    args = p.parse_args()
    lines = ["| model | batch | strategy | shared steps/s | per-env steps/s | per-env / shared |",
             "|---|---|---|---|---|---|"]
    for name in args.models:
        for batch in args.batches:
            env = torchsim.envs.make(name, num_envs=batch, stepper="auto")
            shared = env.stepper
            draw = lambda: torch.empty(batch).uniform_(0.8, 1.2)  # noqa: E731
            env.set_physics(mass_scale=draw(), friction_scale=draw(), actuator_gain_scale=draw())
            per_env = env.stepper
            q, qd = env._sample_init(batch)
            ctrl = torch.rand(batch, env.sys.nu) * 2 - 1
            runs = {}
            for label, stepper in (("shared", shared), ("per-env", per_env)):
                state = [torchsim.init(stepper.sys, q, qd)]

                def run(stepper=stepper, state=state):
                    state[0] = stepper(state[0], ctrl)

                with torch.no_grad():
                    start = time.perf_counter()
                    run()
                    first_s = time.perf_counter() - start
                print(f"{name} batch {batch} {label} ({stepper.strategy}): first step {first_s:.1f} s", flush=True)
                runs[label] = run
            # the ratio: the median of the repeats' ratios (the two take turns within each repeat)
            with torch.no_grad():
                rates = alternating_rates(runs, batch, args.repeats)
            ratio = statistics.median(p / s for p, s in zip(rates["per-env"], rates["shared"]))
            rates = {label: statistics.median(r) for label, r in rates.items()}
            strategy = " / ".join(dict.fromkeys((shared.strategy, per_env.strategy)))
            lines.append(f"| {name} | {batch} | {strategy} | {rates['shared']:,.0f} | {rates['per-env']:,.0f} | "
                         f"{ratio:.2f} |")
            print(lines[-1], flush=True)
    emit_table("\n".join(lines), args.out)


if __name__ == "__main__":
    main()
