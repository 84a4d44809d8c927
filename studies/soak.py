"""Soak: every env at its default settings, thousands of envs for an episode's length of uniform random and of
constant full-range actions, counting the envs whose physics diverged (docs/stability.md).

    python studies/soak.py                                   # every env, 3 action modes, 4096 envs x 1000 steps
    python studies/soak.py --envs ant --modes plus --num-envs 4096
    python studies/soak.py --write-docs                      # also update the table in docs/stability.md

Each (env, mode) run builds the env at its defaults (model, method, substeps, float32, reset distribution, action
mapping, compiled ``stepper="auto"``), fully resets it with seed 0 and steps it ``--steps`` times; an env that ends
(terminated, diverged or truncated) is reset as in training (``maybe_reset``). Action modes: ``random`` (uniform in
the action spec, drawn every step), ``plus`` / ``minus`` (the spec's upper / lower bound on every actuator).

An env counts as diverged if the engine flagged it (``state.diverged``, ``pipeline.contain_divergence``) at any
step, even though its reset clears the flag. To tell which quantity went bad, the physics step that flagged it is
run again with the divergence bounds off (``DivergenceWatch``); the first divergence of each env is recorded (env
step, steps into its episode, quantity, body, value).

Cost, per mode at 4096 envs x 1000 steps on one thread, measured on the shared 2-core machine beside other jobs
(``docs/stability.md`` has every run's wall time): 6-95 s for the pendulums, reacher, hopper and walker2d; 1-2 min
for the halfcheetah, fetch and ur5e_reach; 1.5-3 min for the humanoid, the ant and the pusher (whose diverging envs
make the watch run most steps twice); about 10 min for grasp (xpbd: the ``calls`` strategy). The five locomotion
envs take about 20 min, every env about 65 min. Add a kernel build of 20-60 s per env (grasp: ~5 min of inductor)
after each change to torchsim's source (cached on disk).
Envs that end often cost more: a reset rebuilds their start states eagerly. ``--threads 2`` helps only on an idle
machine: beside other jobs the humanoid ran at 2,100 env-steps/s on 2 threads against 46,000 on one. ``--stepper
eager`` is ~100x slower than the kernel (the ant: ~2 s per 256-env step). Progress lines give the rate and the
run's time left; after each run, an estimate of the soak's time left.
"""

import argparse
import datetime
import sys
import textwrap
import time
import warnings
from pathlib import Path

import torch

from torchsim.envs import ENVS

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))  # the soak test_stability runs short
from stability_runs import MODES, describe, soak, watched_env  # noqa: E402

DOCS_PAGE = Path(__file__).resolve().parent.parent / "docs" / "stability.md"
TABLE_START, TABLE_END = "<!-- soak table: written by studies/soak.py -->", "<!-- end of soak table -->"
SHOW_DIVERGED = 10  # diverged envs printed per run


def write_docs(rows: dict, options: str) -> None:
    """Put ``rows`` ((env, mode) -> table line) into the soak table of docs/stability.md, keeping the rows of
    runs not repeated now, under the command that reproduces the table (``options``: the run's other flags)."""
    text = DOCS_PAGE.read_text()
    if TABLE_START not in text:
        raise SystemExit(f"{DOCS_PAGE} has no {TABLE_START!r} marker: add the soak section first")
    before, rest = text.split(TABLE_START, 1)
    old_table, after = rest.split(TABLE_END, 1)
    kept = {}
    for line in old_table.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("| ") and cells[0] in ENVS:
            kept[(cells[0], cells[1])] = line
    kept.update(rows)
    order = {name: i for i, name in enumerate(ENVS)}
    keys = sorted(kept, key=lambda k: (order[k[0]], MODES.index(k[1])))
    names = list(dict.fromkeys(name for name, _ in keys))
    if names == list(ENVS):
        reproduce = f"Reproduce: `python studies/soak.py{options}`"
    else:
        reproduce = f"Reproduce: `python studies/soak.py --envs NAMES{options}`, NAMES = {','.join(names)}"
    lines = [*textwrap.wrap(reproduce + " (rows written by earlier runs keep their date).", 120,
                            break_long_words=False, break_on_hyphens=False), "",
             "| env | mode | envs x steps | diverged envs | first divergence | episodes ended | env-steps/s | wall "
             "| date | torch threads |", "|---|---|---|---|---|---|---|---|---|---|"]
    lines += [kept[k] for k in keys]
    DOCS_PAGE.write_text(before + TABLE_START + "\n" + "\n".join(lines) + "\n" + TABLE_END + after)
    print(f"updated {DOCS_PAGE}")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", type=lambda s: s.split(","), default=list(ENVS), help="comma-separated names")
    parser.add_argument("--modes", type=lambda s: s.split(","), default=list(MODES), help=f"some of {MODES}")
    parser.add_argument("--num-envs", type=int, default=4096)
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--stepper", default="auto", help="torchsim.Stepper strategy ('auto': the envs' compiled)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (see the cost note above)")
    parser.add_argument("--write-docs", action="store_true", help="update the soak table in docs/stability.md")
    args = parser.parse_args()
    for name in args.envs:
        if name not in ENVS:
            parser.error(f"unknown env {name!r}; available: {', '.join(ENVS)}")
    for mode in args.modes:
        if mode not in MODES:
            parser.error(f"unknown mode {mode!r}; available: {', '.join(MODES)}")
    torch.set_num_threads(args.threads)
    warnings.simplefilter("ignore")  # the env models' ignored <sensor>s
    defaults = parser.parse_args([])
    options = "".join(f" --{k.replace('_', '-')} {v}" for k, v in vars(args).items()
                      if k in ("num_envs", "steps", "stepper") and v != getattr(defaults, k))
    rows, date = {}, datetime.date.today().isoformat()
    runs, done, soak_start = len(args.envs) * len(args.modes), 0, time.perf_counter()
    for name in args.envs:
        env = watched_env(name, args.num_envs, args.stepper)
        print(f"{name}: {env.stepper.stepper.strategy} strategy (its first step builds or loads the compiled code), "
              f"{env.frame_skip} frames x {env.sys.substeps} substeps a step", flush=True)
        for mode in args.modes:
            res = soak(env, mode, args.steps)
            done += 1
            elapsed = time.perf_counter() - soak_start
            print(f"{name} {mode}: {res['diverged']} of {args.num_envs} envs diverged; first: "
                  f"{describe(res['first'])}; {res['ended']} episodes ended; {res['rate']:,.0f} env-steps/s; "
                  f"{res['wall']:.0f} s "
                  f"(soak: {elapsed / 60:.1f} min, about {elapsed / done * (runs - done) / 60:.0f} min to go)",
                  flush=True)
            for env_index, f in res["first"][1:SHOW_DIVERGED]:
                print(f"    also env {env_index}: {describe([(env_index, f)])}")
            rows[(name, mode)] = (f"| {name} | {mode} | {args.num_envs} x {args.steps} | {res['diverged']} | "
                                  f"{describe(res['first'])} | {res['ended']} | {res['rate']:,.0f} | "
                                  f"{res['wall']:.0f} s | {date} | {args.threads} |")
    if args.write_docs:
        write_docs(rows, options)


if __name__ == "__main__":
    main()
