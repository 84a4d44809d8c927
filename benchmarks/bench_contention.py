"""The main job's speed on a machine another program is using: the PPO loop (collector + learner) and a
deterministic evaluation, with 0, 1 and 2 competing single-threaded processes, for each way of running the CPU
kernel's threads. Run it on an otherwise quiet machine:

    python benchmarks/bench_contention.py                         # the main job's settings, every variant, 3 repeats
    python benchmarks/bench_contention.py --variants default threads=1 --loads 0 1 --repeats 5 --nice 0

A competitor is ``python -c "while True: pass"`` (one busy core) at ``--nice`` (default 19: a background job, as
the slowdown was first seen; 0: an equal job). Each measurement is a fresh child process (OpenMP reads its
environment once): it builds the main job's PPO (the kernel comes from the cache after the first), collects and
updates once to warm up, then times whole iterations for ``--seconds``, then ``--eval-steps`` steps of the
evaluation env (``eval.episodes`` envs, deterministic policy). Loads take turns within each repeat, so a drift of
the machine reaches them alike. The table gives each variant's medians and its rate under load as a fraction of
its own idle rate, and of the default's idle rate.

The variants (``--variants``; each sets environment variables or config overrides):

- ``default``: as ``python -m torchsim.train`` runs: idle OpenMP threads spin 1000 times before they sleep
  (``GOMP_SPINCOUNT``, set by ``torchsim`` unless the environment sets it);
- ``libgomp spin``: libgomp's own default, 300,000 spins (torchsim's default before this benchmark);
- ``passive``: ``OMP_WAIT_POLICY=PASSIVE`` (idle OpenMP threads sleep at once);
- ``threads=1``: torch and the kernel on one thread.
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

#: name -> (environment, config overrides)
VARIANTS = {
    "default": ({}, []),
    "libgomp spin": ({"GOMP_SPINCOUNT": "300000"}, []),
    "passive": ({"OMP_WAIT_POLICY": "PASSIVE", "GOMP_SPINCOUNT": "0"}, []),
    "threads=1": ({}, ["threads=1"]),
}


def child(overrides: list[str], seconds: float, eval_steps: int) -> dict:
    """Build the main job's PPO, warm it up, time the loop and an evaluation's steps; the rates as a dict."""
    import torchsim  # noqa: F401  (first, as in python -m torchsim.train: it sets OpenMP's spin before torch loads it)
    import torch
    from hydra import compose, initialize_config_dir
    from tensordict.nn import set_interaction_type
    from torchrl.envs.utils import ExplorationType

    from torchsim.algos.env_factory import make_eval_env
    from torchsim.algos.ppo import PPO
    from torchsim.algos.train import CONFIG_DIR, prepare

    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose(config_name="config", overrides=overrides)
    prepare(cfg)
    ppo = PPO(cfg)
    eval_env = make_eval_env(cfg, ppo.env)
    frames = cfg.algo.num_envs * cfg.algo.unroll
    batches = iter(ppo.collector)
    ppo.update(next(batches), lambda *a: None)  # compiles the loss, loads the kernel
    iterations, start = 0, time.perf_counter()
    while iterations == 0 or time.perf_counter() - start < seconds:
        ppo.update(next(batches), lambda *a: None)
        iterations += 1
    loop = iterations * frames / (time.perf_counter() - start)
    with torch.no_grad(), set_interaction_type(ExplorationType.DETERMINISTIC):
        td = eval_env.reset()
        td = eval_env.step_mdp(eval_env.step(ppo.actor(td)))
        start = time.perf_counter()
        for _ in range(eval_steps):
            td = eval_env.step_mdp(eval_env.step(ppo.actor(td)))
        evaluation = eval_steps * eval_env.batch_size.numel() / (time.perf_counter() - start)
    ppo.collector.shutdown()
    return {"loop": loop, "eval": evaluation, "threads": torch.get_num_threads(), "num_envs": cfg.algo.num_envs,
            "eval_envs": eval_env.batch_size.numel(), "env": cfg.env.name}


def measure(variant: str, load: int, args) -> dict:
    """One child's rates for ``variant`` while ``load`` competitors run."""
    env_vars, overrides = VARIANTS[variant]
    competitors = [subprocess.Popen(["nice", "-n", str(args.nice), sys.executable, "-c", "while True: pass"])
                   for _ in range(load)]
    try:
        done = subprocess.run(
            [sys.executable, __file__, "--child", json.dumps(overrides + args.overrides),
             "--seconds", str(args.seconds), "--eval-steps", str(args.eval_steps)],
            env={**os.environ, **env_vars}, capture_output=True, text=True, timeout=1800)
    finally:
        for p in competitors:
            p.kill()
            p.wait()
    if done.returncode:
        raise RuntimeError(f"{variant} with {load} competitors failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("overrides", nargs="*", help="config overrides, as for python -m torchsim.train")
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    p.add_argument("--loads", nargs="+", type=int, default=[0, 1, 2], help="competing processes")
    p.add_argument("--nice", type=int, default=19, help="the competitors' niceness")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--seconds", type=float, default=10.0, help="least time the loop is timed, per measurement")
    p.add_argument("--eval-steps", type=int, default=200, help="evaluation steps timed, per measurement")
    p.add_argument("--child", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        print(json.dumps(child(json.loads(args.child), args.seconds, args.eval_steps)))
        return
    rates = {(v, n): [] for v in args.variants for n in args.loads}
    first = None
    for repeat in range(args.repeats):
        for v in args.variants:
            for n in args.loads:
                result = measure(v, n, args)
                first = first or result
                rates[v, n].append(result)
                print(f"repeat {repeat + 1}/{args.repeats}  {v:18s} {n} competitors: loop {result['loop']:8,.0f} "
                      f"env-steps/s, eval {result['eval']:8,.0f} env-steps/s", flush=True)
    print(f"\n{first['env']}, training batch {first['num_envs']}, evaluation batch {first['eval_envs']}, "
          f"{os.cpu_count()} CPUs, competitors at nice {args.nice}; medians of {args.repeats}")
    print("\n| variant | competitors | loop env-steps/s | of its idle | of default idle "
          "| eval env-steps/s | of its idle | of default idle |\n|---|---|---|---|---|---|---|---|")
    median = {k: {s: statistics.median(r[s] for r in rs) for s in ("loop", "eval")} for k, rs in rates.items()}
    base = median.get(("default", 0)) or median[args.variants[0], args.loads[0]]
    for (v, n), m in median.items():
        idle = median.get((v, 0), m)
        print(f"| {v} | {n} | {m['loop']:,.0f} | {m['loop'] / idle['loop']:.2f} | {m['loop'] / base['loop']:.2f} "
              f"| {m['eval']:,.0f} | {m['eval'] / idle['eval']:.2f} | {m['eval'] / base['eval']:.2f} |")


if __name__ == "__main__":
    main()
