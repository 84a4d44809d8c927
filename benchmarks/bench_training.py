"""Where a PPO iteration's time goes, side by side in one run, as env-steps/s (samples/s for the learner):

    python benchmarks/bench_training.py                       # the main job's settings (PPO on Ant, config defaults)
    python benchmarks/bench_training.py env=halfcheetah algo.num_envs=1024 --repeats 5

1. engine alone: the env's ``torchsim.Stepper`` x frame_skip on the training batch under random controls (no env, no policy);
2. env alone: ``env.step`` of the TorchRL env with its transforms (observation, reward, resets, normaliser);
3. collector: ``Collector`` batches (engine + policy + transforms), frames per second;
4. learner: ``PPO.update`` on one collected batch (GAE, then epochs x minibatches of Adam steps), samples/s;
5. whole loop: collector and learner in turn, as ``torchsim.train`` runs them.

``--profile-collector N`` then profiles N collector batches (cProfile, by cumulative time): where the env's and
policy's share of the collector goes (resets, normaliser, TorchRL's bookkeeping).

``--learner-variant "key=value ..."`` also times ``PPO.update`` of a second PPO built with those overrides on the
same collected batch, alternating with the first (e.g. ``"algo.value_net.bf16=true algo.policy_net.bf16=true"``).

Hydra-style ``key=value`` overrides select the config (the same composition as ``python -m torchsim.train``); the
compile it asks for happens before timing. Each figure is the median of ``--repeats`` timings; in each repeat the
stages take turns, each timed over whole batches for at least ``--seconds``.
"""

import argparse
import cProfile
import logging
import pstats
import statistics

import torch
from hydra import compose, initialize_config_dir

from _timing import alternating_rates
from torchsim.algos.ppo import PPO
from torchsim.algos.train import CONFIG_DIR, prepare


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("overrides", nargs="*", help="config overrides, as for python -m torchsim.train")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--seconds", type=float, default=2.0, help="least time per stage and repeat (whole batches)")
    p.add_argument("--learner-variant", default=None, help="overrides of a second learner, timed beside the first")
    p.add_argument("--profile-collector", type=int, default=0, metavar="N",
                   help="then profile N collector batches (cProfile, top 40 by cumulative time)")
    args = p.parse_args()
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose(config_name="config", overrides=args.overrides)
    if cfg.algo.name != "ppo":
        raise SystemExit("bench_training.py times the PPO recipe (algo=ppo)")
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    prepare(cfg)
    ppo = PPO(cfg)
    env, a = ppo.env.base_env, cfg.algo
    frames = a.num_envs * a.unroll
    print(f"{cfg.env.name}, batch {a.num_envs}, unroll {a.unroll}, {a.epochs} epochs x {a.minibatches} minibatches, "
          f"compile={cfg.compile}, {torch.get_num_threads()} threads, float32, CPU", flush=True)

    ctrl = torch.rand(a.num_envs, env.sys.nu) * 2 - 1
    state = env.state

    def engine():
        s = state
        for _ in range(a.unroll):
            for _ in range(env.frame_skip):
                s = env.stepper(s, ctrl)

    def env_steps():
        td = ppo.env.reset()
        for _ in range(a.unroll):
            td["action"] = ppo.env.action_spec.rand()
            td = ppo.env.step_mdp(ppo.env.step(td))

    batches = iter(ppo.collector)
    data = next(batches)  # compiles the step (and, with it, everything the first batch needs)
    engine()
    ppo.update(data.clone(), lambda *args: None)  # compiles the loss
    def iteration():
        ppo.update(next(batches), lambda *args: None)

    stages = {"engine alone (env.stepper)": engine, "env alone (env.step + transforms)": env_steps,
              "collector (env + policy)": lambda: next(batches),
              "learner (PPO.update)": lambda: ppo.update(data.clone(), lambda *args: None),
              "whole loop (collector + learner)": iteration}
    # The stages take turns within each repeat, each timed over whole batches for at least --seconds, so a drift
    # of this machine's speed reaches them all alike; each stage's ratio to the engine is taken within its repeat.
    rates = alternating_rates(stages, frames, args.repeats, args.seconds)
    engine_rates = rates["engine alone (env.stepper)"]
    print(f"\n| stage | env-steps/s (median of {args.repeats}) | of engine alone (median of the repeats' ratios) |"
          "\n|---|---|---|")
    for name, stage_rates in rates.items():
        ratio = statistics.median(r / e for r, e in zip(stage_rates, engine_rates))
        print(f"| {name} | {statistics.median(stage_rates):,.0f} | {ratio:.2f} |")
    if args.learner_variant:
        print_learner_variant(args, data, frames, ppo)
    if args.profile_collector:
        profile = cProfile.Profile()
        profile.runcall(lambda: [next(batches) for _ in range(args.profile_collector)])
        pstats.Stats(profile).sort_stats("cumulative").print_stats(40)
    ppo.collector.shutdown()


def print_learner_variant(args, data, frames: int, ppo: PPO) -> None:
    """Print the samples/s of ``PPO.update`` for a PPO built with ``args.learner_variant`` on top of
    ``args.overrides`` beside ``ppo``'s, the two alternating repeat by repeat on the same batch ``data``."""
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose(config_name="config", overrides=[*args.overrides, *args.learner_variant.split()])
    other = PPO(cfg)
    other.update(data.clone(), lambda *a: None)  # compiles its loss
    rates = alternating_rates({"first": lambda: ppo.update(data.clone(), lambda *a: None),
                               "variant": lambda: other.update(data.clone(), lambda *a: None)},
                              frames, args.repeats, args.seconds)
    first, variant = (statistics.median(rates[k]) for k in ("first", "variant"))
    print(f"learner side by side (samples/s, medians of {args.repeats}): as configured {first:,.0f}, "
          f"{args.learner_variant} {variant:,.0f}")
    other.collector.shutdown()


if __name__ == "__main__":
    main()
