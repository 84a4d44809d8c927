"""End-to-end throughput of PPO on PointNav (simulate + render 64x64 depth + policy + learning), in env steps/s:

    python benchmarks/bench_pointnav.py threads=1                      # the recipe: env=pointnav + tuned/ppo_pointnav
    python benchmarks/bench_pointnav.py threads=2 algo.num_envs=256 --repeats 5
    python benchmarks/bench_pointnav.py threads=1 --checkpoint outputs/.../checkpoints/last.pt   # a trained policy

Stages, each the median of ``--repeats`` timings of one training batch (``num_envs x unroll`` env steps):

1. env alone: ``env.step_and_maybe_reset`` with the transforms, under random actions that STOP with probability
   ``--stop-prob`` (else uniform): episode length, and so the share of resets (a wavefront each), set by hand;
2. policy alone: the actor's forward pass on the batch's observations (no gradient);
3. collector: ``Collector`` batches (env + policy) with the recipe's policy (its episodes, its resets);
4. learner: ``PPO.update`` on one collected batch (GAE, then epochs x minibatches of optimiser steps), samples/s;
5. whole loop: collector and learner in turn, as ``torchsim.train`` runs them, and the share of each.

The policy is the untrained one unless ``--checkpoint`` loads a run's networks (a trained policy STOPs rarely, so
its episodes are longer and resets fewer). The load average is printed before and after: the machine may be shared.
"""

import argparse
import logging
import os
import time

import torch
from hydra import compose, initialize_config_dir

from _timing import median_rate
from torchsim.algos.checkpoints import load_checkpoint
from torchsim.algos.ppo import PPO
from torchsim.algos.train import CONFIG_DIR, prepare


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("overrides", nargs="*", help="config overrides, as for python -m torchsim.train")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--stop-prob", type=float, default=0.01, help="STOP probability of the env-alone stage's actions")
    p.add_argument("--checkpoint", default=None, help="a run's checkpoints/last.pt: time its trained networks")
    args = p.parse_intermixed_args()  # overrides may follow the options
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose(config_name="config", overrides=["env=pointnav", *args.overrides])
    if cfg.algo.name != "ppo" or cfg.env.name != "pointnav":
        raise SystemExit("bench_pointnav.py times the PPO recipe on pointnav (algo=ppo)")
    ckpt = load_checkpoint(args.checkpoint) if args.checkpoint else None  # a bad file fails before the build
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    prepare(cfg)
    ppo = PPO(cfg)
    if ckpt is not None:
        for key in ("loss", "obs_norm"):
            ppo.state()[key].load_state_dict(ckpt["state"][key])
    a = cfg.algo
    frames = a.num_envs * a.unroll
    print(f"pointnav {ppo.env.base_env.image_size}x{ppo.env.base_env.image_size} depth, batch {a.num_envs}, unroll "
          f"{a.unroll} ({frames} env steps per update), {a.epochs} epochs x {a.minibatches} minibatches, "
          f"{torch.get_num_threads()} threads, {'trained' if args.checkpoint else 'untrained'} policy, "
          f"load average before {os.getloadavg()[0]:.2f}", flush=True)

    env = ppo.env
    td = env.reset()

    def env_alone():
        nonlocal td
        for _ in range(a.unroll):
            stop = torch.rand(a.num_envs) < args.stop_prob
            td["action"] = torch.where(stop, 0, torch.randint(1, 4, (a.num_envs,)))
            _, td = env.step_and_maybe_reset(td)

    batches = iter(ppo.collector)
    data = next(batches)
    obs = data.select(*ppo.actor.in_keys).reshape(-1)

    @torch.no_grad()
    def policy_alone():
        ppo.actor(obs.clone())

    def rate(fn):
        return median_rate(fn, frames, args.repeats, min_seconds=0)

    rows = {f"env alone (random actions, STOP p={args.stop_prob})": rate(env_alone),
            "policy alone (actor forward)": rate(policy_alone),
            "collector (env + policy)": rate(lambda: next(batches)),
            "learner (PPO.update)": rate(lambda: ppo.update(data.clone(), lambda *args: None))}
    times = {"collect": [], "learn": []}

    def iteration():
        t0 = time.perf_counter()
        batch = next(batches)
        t1 = time.perf_counter()
        ppo.update(batch, lambda *args: None)
        times["collect"].append(t1 - t0)
        times["learn"].append(time.perf_counter() - t1)

    rows["whole loop (collector + learner)"] = rate(iteration)
    episodes = data["next", "done"].sum().item()
    collect, learn = sum(times["collect"]), sum(times["learn"])
    print(f"\n| stage | env steps/s (median of {args.repeats}) |\n|---|---:|")
    for name, value in rows.items():
        print(f"| {name} | {value:,.0f} |")
    print(f"\nwhole loop: collection {collect / (collect + learn):.0%}, learning {learn / (collect + learn):.0%} of "
          f"the time; the first collected batch ended {episodes} episodes ({frames / max(episodes, 1):.0f} env steps "
          f"per episode); load average after {os.getloadavg()[0]:.2f}")
    ppo.collector.shutdown()


if __name__ == "__main__":
    main()
