"""The peer run: Brax's own PPO on Brax's Ant, with Brax's tuned settings, timed on this machine.

Brax is not a project dependency; run this in a scratch environment:

    python -m venv /tmp/braxenv && /tmp/braxenv/bin/pip install brax==0.14.2 jax==0.7.2 jaxlib==0.7.2
    /tmp/braxenv/bin/python benchmarks/brax_peer_ppo_ant.py --minutes 35 --out docs/logs/brax_ppo_ant.csv

Settings: Brax's tuned Ant row (2048 envs, batch 1024, 32 minibatches, unroll 5, 4 updates per batch, gamma 0.97,
reward scaling 10, entropy 1e-2, lr 3e-4, 1000-step episodes, normalised observations), the ``spring`` backend
(Brax's fastest on CPU), and a deterministic evaluation over 128 fresh starts, as ``python -m torchsim.train``
evaluates (mean return of episodes up to 1000 steps). Each evaluation prints and appends a CSV row: wall-clock
seconds since this script started (JAX's compile included), env steps, eval return. The run stops itself after
``--minutes``.
"""

import argparse
import csv
import time

T0 = time.perf_counter()


class OutOfTime(Exception):
    pass


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--minutes", type=float, default=35.0)
    p.add_argument("--steps", type=int, default=20_000_000, help="Brax's num_timesteps (evaluations spread over it)")
    p.add_argument("--evals", type=int, default=40)
    p.add_argument("--out", default="brax_ppo_ant.csv")
    args = p.parse_args()

    import jax
    from brax import envs
    from brax.training.agents.ppo import train as ppo

    print(f"jax {jax.__version__} on {jax.devices()}", flush=True)
    env = envs.get_environment("ant", backend="spring")
    with open(args.out, "w", newline="") as f:
        csv.writer(f).writerow(["wall_s", "env_steps", "eval_return"])

    def progress(step, metrics):
        wall = time.perf_counter() - T0
        ret = float(metrics["eval/episode_reward"])
        print(f"[{wall / 60:5.1f} min] env steps {step:>10,}  eval return {ret:8.1f}", flush=True)
        with open(args.out, "a", newline="") as f:
            csv.writer(f).writerow([f"{wall:.1f}", step, f"{ret:.2f}"])
        if wall > args.minutes * 60:
            raise OutOfTime

    try:
        ppo.train(environment=env, num_timesteps=args.steps, num_evals=args.evals, reward_scaling=10,
                  episode_length=1000, normalize_observations=True, action_repeat=1, unroll_length=5,
                  num_minibatches=32, num_updates_per_batch=4, discounting=0.97, learning_rate=3e-4,
                  entropy_cost=1e-2, num_envs=2048, batch_size=1024, seed=0, deterministic_eval=True,
                  num_eval_envs=128, progress_fn=progress)
    except OutOfTime:
        print(f"stopped after {args.minutes} min", flush=True)


if __name__ == "__main__":
    main()
