"""Soak: every env at its default settings, thousands of envs for an episode's length of uniform random and of
constant full-range actions, counting the envs whose physics diverged (issue 27, item 8; docs/stability.md).

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
import math
import textwrap
import time
import warnings
from pathlib import Path

import torch
from torchrl.envs.utils import step_mdp

import torchsim
from torchsim.envs import ENVS, make

DOCS_PAGE = Path(__file__).resolve().parent.parent / "docs" / "stability.md"
TABLE_START, TABLE_END = "<!-- soak table: written by studies/soak.py -->", "<!-- end of soak table -->"
MODES = ("random", "plus", "minus")
PROGRESS_EVERY = 100  # env steps between progress lines
ESTIMATE_AFTER = 20  # env steps timed (after the first, which builds the compiled step) before the estimate
SHOW_DIVERGED = 10  # diverged envs printed per run


class DivergenceWatch:
    """The env's stepper, recording the first divergence of every env: when the engine flags an env, the same
    physics step is run again from the same state with the divergence bounds off, to see which quantity broke.

    ``first`` holds, per env, the first divergence since the soak began as a dict (env step, step in its
    episode, quantity, body, value); ``env_step`` and ``episode_step`` are set by the soak loop before each env
    step."""

    def __init__(self, stepper: torchsim.Stepper):
        self.stepper = stepper
        self.sys = stepper.sys  # the env reads its System here
        self.unbounded = None  # the same step with the bounds off, built on the first divergence
        self.env_step, self.episode_step = 0, None
        self.first = {}

    def __call__(self, state: torchsim.State, ctrl: torch.Tensor) -> torchsim.State:
        new = self.stepper(state, ctrl)
        newly = new.diverged & ~state.diverged
        if newly.any():
            if self.unbounded is None:
                unbounded_sys = self.sys.replace(max_speed=math.inf, max_distance=math.inf)
                self.unbounded = torchsim.Stepper(unbounded_sys, self.stepper.strategy)
            unchecked = self.unbounded(state, ctrl)
            for env in newly.nonzero().flatten().tolist():
                self.first.setdefault(env, dict(env_step=self.env_step, episode_step=int(self.episode_step[env]),
                                                **self.what_broke(unchecked, env)))
        return new

    def what_broke(self, unchecked: torchsim.State, env: int) -> dict:
        """The quantity of env ``env``'s state ``unchecked`` (stepped with the bounds off) that fails the bounds,
        in ``contain_divergence``'s terms: non-finite (then frozen: ``diverged`` set), position, linear speed,
        angular speed."""
        if unchecked.diverged[env]:
            return dict(quantity="non-finite", body="-", value=math.nan)
        for quantity, values, bound in (("distance [m]", unchecked.x_pos, self.sys.max_distance),
                                        ("linear speed [m/s]", unchecked.xd_vel, self.sys.max_speed),
                                        ("angular speed [rad/s]", unchecked.xd_ang, self.sys.max_speed)):
            per_body = values[env].abs().amax(-1)
            if per_body.max() >= bound:
                body = int(per_body.argmax())
                return dict(quantity=quantity, body=self.sys.body_names[body], value=float(per_body[body]))
        return dict(quantity="not reproduced", body="-", value=math.nan)


def watched_env(name: str, num_envs: int, stepper: str = "auto"):
    """Env ``name`` at its defaults with ``num_envs`` envs, stepping through a :class:`DivergenceWatch`."""
    env = make(name, num_envs=num_envs, stepper=stepper)
    env.stepper = DivergenceWatch(env.stepper)
    return env


def constant_action(env, mode: str) -> torch.Tensor:
    """The action of ``mode``: the action spec's upper (``plus``) or lower (``minus``) bound for every env."""
    spec = env.action_spec
    return (spec.space.high if mode == "plus" else spec.space.low).expand(spec.shape).clone()


def soak(env, mode: str, steps: int, seed: int = 0) -> dict:
    """Step ``env`` ``steps`` times under action mode ``mode`` with resets; the diverged envs and the rate."""
    watch = env.stepper
    watch.first = {}
    torch.manual_seed(seed)
    td = env.reset()
    action = None if mode == "random" else constant_action(env, mode)
    ended = 0
    start = time.perf_counter()
    timed_from = None
    for t in range(steps):
        watch.env_step, watch.episode_step = t, env.step_count.clone()
        td["action"] = env.action_spec.rand() if action is None else action
        td = env.step(td)
        ended += int(td["next", "done"].sum())
        td = env.maybe_reset(step_mdp(td))
        if t == 0:
            timed_from = time.perf_counter()  # the first step builds (or loads) the compiled step
        if t > 0 and (t == ESTIMATE_AFTER or (t + 1) % PROGRESS_EVERY == 0 or t + 1 == steps):
            rate = t * env.batch_size[0] / max(time.perf_counter() - timed_from, 1e-9)
            print(f"  {type(env).__name__} {mode}: step {t + 1}/{steps}, {rate:,.0f} env-steps/s, diverged envs "
                  f"{len(watch.first)}, ETA {(steps - t - 1) * env.batch_size[0] / rate:.0f} s", flush=True)
    wall = time.perf_counter() - start
    rate = (steps - 1) * env.batch_size[0] / (time.perf_counter() - timed_from) if steps > 1 else math.nan
    return dict(diverged=len(watch.first), first=sorted(watch.first.items(), key=lambda e: e[1]["env_step"]),
                ended=ended, rate=rate, wall=wall)


def describe(first: list) -> str:
    """The earliest divergence of a run, for the table."""
    if not first:
        return "-"
    env, f = first[0]
    value = "" if math.isnan(f["value"]) else f" = {f['value']:.3g}"
    return (f"step {f['env_step']} (episode step {f['episode_step']}), env {env}: {f['quantity']} of "
            f"{f['body']}{value}")


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
