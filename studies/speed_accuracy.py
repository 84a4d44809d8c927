"""Speed against accuracy, torchsim next to MuJoCo C, per model: torchsim's solution method x substeps x dtype and
MuJoCo's integrator x timestep, each point's throughput next to its error against MuJoCo at a 10x finer timestep.

    python studies/speed_accuracy.py            # full sweep: docs/speed_accuracy.csv + PNGs (read in the .md)
    python studies/speed_accuracy.py --quick    # smoke run (2 models, 1 setting, eager): /tmp/speed_accuracy
    python studies/speed_accuracy.py --models ant --methods spring_soft --dtypes float32 --merge --no-mujoco
                                                # add spring with MuJoCo's soft contacts (load_mjcf's contact_model)

Models: ``pendulum`` (the tests' triple pendulum, 1 ms, a +-2 N m motor on each hinge), ``ur5e``
(envs/assets/ur5e.urdf through torchsim's URDF translation, armature 0.1, 2 ms), both with contacts disabled, and
the ``ant``, ``halfcheetah`` and ``humanoid`` envs (envs/assets, their frame_skip).

Accuracy: every point runs the same scenarios from the same start with the same open-loop controls (held for an
env step) as the reference, MuJoCo at timestep / 10 with the MJCF's integrator (Euler for all five), float64 there:

- contact-free models: ``joint_rms_rad`` = RMS over the horizon and the joints of the angle difference to the
  reference, ``joint_max_rad`` its max. Pendulum: 1 s from (0.8, -0.4, 0.6) rad under fixed-seed random torques
  in the full +-2 N m; UR5e: 0.4 s from q = 0 (arm horizontal) under fixed-seed random torques in 10% of the
  effort limits; a new torque every model timestep.
- contact models, measures that do not hinge on chaos: ``settle_err_m`` = |root height - reference| after
  ``settle`` s with zero control from the initial pose (ant, halfcheetah: at rest after 2 s; humanoid: 0.5 s into
  its collapse, before it topples, the moment MuJoCo's own settings agree on); ``root_err_m`` = max |root position
  - reference| over 0.25 s of full-range random controls (studies/check_models.py's check, from
  tests/model_rollouts.py), short enough that MuJoCo's settings still agree to ~1 cm.
- ``anchor_gap_m``: torchsim's joint constraint violation, the largest joint-anchor separation seen at any env step
  of these runs (MuJoCo, in generalized coordinates, has none). ``diverged``: torchsim's divergence flag.

Speed: ``steps_per_s`` = model timesteps simulated per second over each of ``--batches`` envs on ``--threads``
threads (``env_steps_per_s`` = that / frame_skip); torchsim with a ``torchsim.Stepper`` at its default strategy (the
step kernel for spring on CPU; a kernel bakes the substep length in, so each substep count builds its own), MuJoCo C
with ``mujoco.rollout`` on as many threads, same batch, same start, in the same run; median of ``--repeats``. A
point's errors do not depend on the batch: they are measured once and repeated in its row for each batch, and each
batch gets its own chart and Pareto fronts.
"""

import argparse
import csv
import dataclasses
import os
import sys
import time
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Callable
from pathlib import Path

import mujoco
import numpy as np
import torch

import torchsim
from torchsim.envs import ENVS
from torchsim.io_urdf import urdf_to_mjcf
from torch._dynamo.utils import counters
from torchsim.kinematics import anchor_gap

REPO = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(REPO / "benchmarks"), str(REPO / "tests")]  # the timing helpers, the reference models
import model_rollouts  # the model checks' starts and actions (tests/model_rollouts.py)
from _speed_accuracy_plot import plot_model
from _timing import allow_recompiles, median_rate, mujoco_rollout_rate, mujoco_start_states
from test_mujoco_reference import TRIPLE

REFERENCE_FACTOR = 10  # the reference runs at timestep / 10
MUJOCO_INTEGRATORS = {"Euler": mujoco.mjtIntegrator.mjINT_EULER, "RK4": mujoco.mjtIntegrator.mjINT_RK4,
                      "implicitfast": mujoco.mjtIntegrator.mjINT_IMPLICITFAST}
MUJOCO_FACTORS = (1, 2, 4)  # MuJoCo points at timestep / factor
DTYPES = {"float32": torch.float32, "float64": torch.float64}
# torchsim's series, each a load_mjcf setting: the two methods, and spring with MuJoCo's soft contact normal
LOAD_OPTIONS = {"spring": dict(method="spring"), "xpbd": dict(method="xpbd"),
                "spring_soft": dict(method="spring", contact_model="soft")}
ERRORS = {True: ("joint_rms_rad", "joint_max_rad"), False: ("settle_err_m", "root_err_m")}  # by contact_free
SPEED_STEPS = 20  # model timesteps per timed MuJoCo rollout
# Envs per accuracy run (the scenarios, repeated): a size no model dimension has, since the compiler gives dims of
# equal size one symbol and a model dimension's guard (e.g. ctrlrange's 2) would then pin the batch and force a
# second compile for the timed batch
ACCURACY_BATCH = 64


@dataclasses.dataclass(frozen=True)
class Model:
    """One swept model. ``start(m)`` -> (q0, qd0); ``controls(m)`` -> one (env steps, nu) array per scenario."""

    mjcf: str
    frame_skip: int  # model timesteps per env step (1 where there is no env)
    default_substeps: int | None  # the env's choice; None: load_mjcf's 0.5 ms substeps
    substeps: tuple[int, ...]
    contact_free: bool
    start: Callable
    controls: Callable
    # (method, dtype) pairs swept, one compile each (2-5 min on the shared 2-core VM: they dominate the run time).
    # float64 only where errors are small enough for rounding to show (the contact-free models), and xpbd float64
    # only on the pendulum, where it shows xpbd's float32 velocities (x_new - x_old) / h losing digits as h shrinks
    settings: tuple = (("spring", "float32"), ("xpbd", "float32"))


def _without_contacts(mjcf: str) -> str:
    """The MJCF with contacts disabled (both engines read ``<option><flag contact="disable"/>``)."""
    root = ET.fromstring(mjcf)
    option = root.find("option")
    option = ET.SubElement(root, "option") if option is None else option
    ET.SubElement(option, "flag", contact="disable")
    return ET.tostring(root, encoding="unicode")


def _with_motors(mjcf: str, gear: float) -> str:
    """The MJCF with a motor on every hinge (gear ``gear``, ctrlrange +-1)."""
    root = ET.fromstring(mjcf)
    actuators = ET.SubElement(root, "actuator")
    for i, joint in enumerate(root.iter("joint")):
        joint.set("name", f"hinge{i}")
        ET.SubElement(actuators, "motor", joint=f"hinge{i}", gear=str(gear), ctrlrange="-1 1", ctrllimited="true")
    return ET.tostring(root, encoding="unicode")


def _fixed_start(q0) -> Callable:
    return lambda m: (np.array(q0, dtype=float), np.zeros(m.nv))


def _random_torques(horizon: float, scale: float, seed: int = 0) -> Callable:
    """One scenario: fixed-seed uniform controls in ``scale`` x the ctrlrange, one row per model timestep."""
    def controls(m):
        lo, hi = m.actuator_ctrlrange.T
        steps = round(horizon / m.opt.timestep)
        return [np.random.default_rng(seed).uniform(lo, hi, (steps, m.nu)) * scale]
    return controls


def _settle_and_random(name: str, settle: float) -> Callable:
    """Two scenarios: zero control for ``settle`` s, and model_rollouts' 0.25 s of full-range random controls."""
    def controls(m):
        steps = round(settle / (m.opt.timestep * ENVS[name].frame_skip))
        return [np.zeros((steps, m.nu)), model_rollouts.actions(name, m)]
    return controls


def _env(name: str, settle: float) -> Model:
    env = ENVS[name]
    default = env.substeps or torchsim.load_mjcf(model_rollouts.path(name)).substeps
    return Model(Path(model_rollouts.path(name)).read_text(), env.frame_skip, env.substeps,
                 (default // 2, default, 2 * default), False, lambda m: model_rollouts.initial_state(name, m),
                 _settle_and_random(name, settle))


WITH_FLOAT64 = (("spring", "float32"), ("xpbd", "float32"), ("spring", "float64"))
ALL_SETTINGS = (*WITH_FLOAT64, ("xpbd", "float64"))
MODELS = {
    "pendulum": Model(_with_motors(_without_contacts(TRIPLE), 2.0), 1, None, (1, 2, 4, 8, 16), True,
                      _fixed_start((0.8, -0.4, 0.6)), _random_torques(1.0, 1.0), ALL_SETTINGS),
    "ur5e": Model(_without_contacts(urdf_to_mjcf(REPO / "envs" / "assets" / "ur5e.urdf", armature=0.1)), 1, None,
                  (2, 4, 8, 16), True, _fixed_start(np.zeros(6)), _random_torques(0.4, 0.1), WITH_FLOAT64),
    "ant": _env("ant", 2.0),
    "halfcheetah": _env("halfcheetah", 2.0),
    "humanoid": _env("humanoid", 0.5),
}


def log(msg: str) -> None:
    print(msg, flush=True)


def mujoco_model(model: Model, factor: int = 1, integrator: str | None = None) -> mujoco.MjModel:
    """The model's MjModel at timestep / ``factor`` with ``integrator`` (None: the MJCF's)."""
    m = mujoco.MjModel.from_xml_string(model.mjcf)
    m.opt.timestep /= factor
    if integrator is not None:
        m.opt.integrator = MUJOCO_INTEGRATORS[integrator]
    return m


def mujoco_runs(model: Model, factor: int = 1, integrator: str | None = None) -> list:
    """Per scenario, MuJoCo's (qpos, root xpos) per env step at timestep / ``factor``."""
    m0 = mujoco_model(model)
    m = mujoco_model(model, factor, integrator)
    return [model_rollouts.mujoco_trajectory(m, *model.start(m0), acts, model.frame_skip * factor)
            for acts in model.controls(m0)]


def torchsim_runs(stepper: torchsim.Stepper, model: Model, m: mujoco.MjModel):
    """All scenarios side by side in one batch of ACCURACY_BATCH envs: per scenario (q, root xpos) per env step, the
    largest anchor gap seen at any env step, and whether any env diverged."""
    system = stepper.sys
    controls = model.controls(m)
    steps = max(len(c) for c in controls)
    batch = ACCURACY_BATCH
    ctrl = np.zeros((steps, batch, m.nu))
    for e in range(batch):
        acts = controls[e % len(controls)]
        ctrl[:len(acts), e] = acts
    # one tensor per env step, not views of one: the compiled substep guards on a view's base and strides
    ctrl = [torch.tensor(c, dtype=system.dtype, device=system.device) for c in ctrl]
    q0, qd0 = (torch.tensor(np.tile(x, (batch, 1)), dtype=system.dtype, device=system.device) for x in model.start(m))
    state = torchsim.init(system, q0, qd0)

    states = [state]
    for k in range(steps):
        for _ in range(model.frame_skip):
            state = stepper(state, ctrl[k])
        states.append(state)
    # (env step, env) flattened into one batch: one kinematics call instead of one per env step
    history = torchsim.State(*(torch.cat(x) for x in zip(*states)))
    roots = torchsim.mj_body_poses(system, history.x_pos, history.x_quat)[0][:, 1].reshape(steps + 1, batch, 3)
    qs = history.q.reshape(steps + 1, batch, -1)
    qs, roots = (x.transpose(0, 1).double().cpu().numpy() for x in (qs, roots))
    runs = [(qs[e, :len(c) + 1], roots[e, :len(c) + 1]) for e, c in enumerate(controls)]
    diverged = bool(state.diverged.any()) or not bool(torch.isfinite(state.q).all())
    return runs, float(anchor_gap(system, history).max()), diverged


def errors(model: Model, runs: list, ref: list) -> dict:
    """The model's error measures of ``runs`` against ``ref`` (per scenario (q, root) trajectories)."""
    if model.contact_free:
        diff = runs[0][0][1:] - ref[0][0][1:]  # hinge angles are continuous in both engines
        return {"joint_rms_rad": float(np.sqrt(np.mean(diff**2))), "joint_max_rad": float(np.abs(diff).max())}
    (_, settle), (_, settle_ref) = runs[0], ref[0]
    (_, moved), (_, moved_ref) = runs[1], ref[1]
    return {"settle_err_m": float(abs(settle[-1, 2] - settle_ref[-1, 2])),
            "root_err_m": float(np.abs(moved - moved_ref).max())}


def random_controls(m: mujoco.MjModel, shape: tuple) -> np.ndarray:
    """Fixed-seed uniform controls in the ctrlrange, ``shape + (nu,)``: the load the speed is timed under."""
    lo, hi = m.actuator_ctrlrange.T
    return np.random.default_rng(0).uniform(lo, hi, shape + (m.nu,))


def one_step(stepper: torchsim.Stepper, m: mujoco.MjModel) -> None:
    """One step of ACCURACY_BATCH envs at qpos0."""
    system = stepper.sys
    def zeros(n):
        return torch.zeros(ACCURACY_BATCH, n, dtype=system.dtype, device=system.device)

    q0 = torch.tensor(np.tile(m.qpos0, (ACCURACY_BATCH, 1)), dtype=system.dtype, device=system.device)
    stepper(torchsim.init(system, q0, zeros(system.nv)), zeros(system.nu))


def torchsim_rate(stepper: torchsim.Stepper, model: Model, m: mujoco.MjModel, batch: int, repeats: int) -> float:
    """Model timesteps/s of ``stepper`` over ``batch`` envs from the model's start, random controls."""
    system = stepper.sys
    q0, qd0 = (torch.tensor(np.tile(x, (batch, 1)), dtype=system.dtype, device=system.device) for x in model.start(m))
    ctrl = torch.tensor(random_controls(m, (batch,)), dtype=system.dtype, device=system.device)
    state = [torchsim.init(system, q0, qd0)]

    def run():
        state[0] = stepper(state[0], ctrl)
        if system.device.type == "cuda":
            torch.cuda.synchronize()

    run()  # warm-up
    return median_rate(run, batch, repeats)


def mujoco_rate(model: Model, factor: int, integrator: str, batch: int, args) -> float:
    """Model timesteps/s of ``mujoco.rollout`` (``args.threads`` threads) at timestep / ``factor``: controls held per
    timestep."""
    m = mujoco_model(model, factor, integrator)
    q0, qd0 = model.start(m)
    start = mujoco_start_states(m, np.tile(q0, (batch, 1)), np.tile(qd0, (batch, 1)))
    ctrl = random_controls(m, (batch, SPEED_STEPS)).repeat(factor, axis=1)
    return mujoco_rollout_rate(m, start, ctrl, args.repeats, threads=args.threads) / factor


def row(name: str, model: Model, engine: str, method: str, dtype: str, substeps: int, timestep: float, batch: int,
        steps_per_s: float, errs: dict, args, **extra) -> dict:
    """One CSV row. ``substeps``: steps per model timestep (torchsim's substeps; MuJoCo's timestep factor)."""
    return dict(model=name, engine=engine, method=method, dtype=dtype, substeps=substeps, timestep_s=timestep,
                h_s=timestep / substeps, frame_skip=model.frame_skip, batch=batch, threads=args.threads,
                device=args.device if engine == "torchsim" else "cpu", steps_per_s=steps_per_s,
                env_steps_per_s=steps_per_s / model.frame_skip, **errs, **extra)


def mujoco_points(name: str, model: Model, ref: list, args) -> list[dict]:
    """MuJoCo C's own points: each integrator at timestep / factor for each factor, timed at each batch."""
    points = [("Euler", 1)] if args.quick else [(i, f) for i in MUJOCO_INTEGRATORS for f in MUJOCO_FACTORS]
    rows, timestep = [], mujoco_model(model).opt.timestep
    for integrator, factor in points:
        t0 = time.perf_counter()
        errs = errors(model, mujoco_runs(model, factor, integrator), ref)
        for batch in args.batches:
            r = row(name, model, "mujoco", integrator, "float64", factor, timestep, batch,
                    mujoco_rate(model, factor, integrator, batch, args), errs, args,
                    default=integrator == "Euler" and factor == 1)
            rows.append(r)
            log(f"{describe(r)} ({time.perf_counter() - t0:.0f} s)")
    return rows


def torchsim_points(name: str, model: Model, ref: list, method: str, dtype: str, args) -> list[dict]:
    """torchsim's points of one method and dtype over the model's substep counts (one compile serves them all)."""
    m = mujoco_model(model)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        base = torchsim.load_mjcf(model.mjcf, dtype=DTYPES[dtype], device=args.device, **LOAD_OPTIONS[method])
    default = model.default_substeps or base.substeps
    one_step(torchsim.Stepper(base, "eager"), m)  # eager first: fills torchsim.spatial's per-dtype constant
    # tables, which a compiled graph traced before they exist guards on, and would be compiled a second time
    compile_s = 0.0
    stepper = torchsim.Stepper(base, "eager" if args.eager else "auto")
    if not args.eager:
        t0 = time.perf_counter()
        one_step(stepper, m)
        compile_s = time.perf_counter() - t0
        log(f"{name}: compiled the {method} {dtype} substep in {compile_s:.0f} s")
    rows = []
    for substeps in [default] if args.quick else model.substeps:
        t0 = time.perf_counter()
        sys_ = base.replace(substeps=substeps)
        sub_stepper = stepper.for_system(sys_)  # one per substep count: a row graph bakes the substep length in
        runs, gap, diverged = torchsim_runs(sub_stepper, model, m)
        errs = errors(model, runs, ref)
        for batch in args.batches:
            r = row(name, model, "torchsim", method, dtype, substeps, base.timestep, batch,
                    torchsim_rate(sub_stepper, model, m, batch, args.repeats), errs, args, anchor_gap_m=gap,
                    diverged=diverged, compiled=not args.eager, compile_s=compile_s, strategy=stepper.strategy,
                    default=method == "spring" and dtype == "float32" and substeps == default)
            rows.append(r)
            log(f"{describe(r)} ({time.perf_counter() - t0:.0f} s)")
    if not args.eager:  # one graph per setting expected; more would mean recompiles (e.g. per substep length)
        log(f"{name}: {counters['stats']['unique_graphs']} substep graphs compiled so far for this model")
    return rows


def describe(r: dict) -> str:
    errs = ", ".join(f"{k} {r[k]:.2e}" for k in (*ERRORS[True], *ERRORS[False], "anchor_gap_m") if k in r)
    return (f"{r['model']:>11} {r['engine']:>8} {r['method']:>12} {r['dtype']:>7} substeps {r['substeps']:>2} "
            f"h {r['h_s'] * 1e3:.3g} ms, batch {r['batch']:>4}: {r['env_steps_per_s']:>10,.0f} env-steps/s, {errs}"
            + ("  DIVERGED" if r.get("diverged") else "") + ("  [default]" if r["default"] else ""))


def pareto(rows: list[dict], metric: str, tie: float = 0.02) -> set[int]:
    """Indices of the rows no other row beats on env-steps/s (higher) at an equal or lower ``metric``; errors within
    ``tie`` (relative) count as equal (e.g. RK4 at every timestep, all at the reference's own error)."""
    ok = [i for i, r in enumerate(rows) if np.isfinite(r[metric]) and not r.get("diverged")]
    return {i for i in ok if not any(rows[j][metric] <= rows[i][metric] * (1 + tie)
                                     and rows[j]["env_steps_per_s"] > rows[i]["env_steps_per_s"] for j in ok)}


def _parse(value: str):
    if value in ("True", "False"):
        return value == "True"
    for kind in (int, float):
        try:
            return kind(value)
        except ValueError:
            pass
    return value


def read_csv(path: Path) -> list[dict]:
    """Rows written by ``write_csv``, typed back (bools, ints, floats); empty cells dropped."""
    with open(path, newline="") as f:
        return [{k: _parse(v) for k, v in r.items() if v != ""} for r in csv.DictReader(f)]


def merge(old: list[dict], new: list[dict]) -> list[dict]:
    """``old`` with the points ``new`` measured again replaced, in model, batch, engine, method, dtype, substeps
    order."""
    def key(r):
        return (list(MODELS).index(r["model"]), -r["batch"], r["engine"], r["method"], r["dtype"], r["substeps"])

    return sorted({key(r): r for r in old + new}.values(), key=key)


def write_csv(rows: list[dict], path: Path) -> None:
    columns = list(dict.fromkeys(k for r in rows for k in r))
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, columns)
        writer.writeheader()
        writer.writerows({k: f"{v:.6g}" if isinstance(v, float) else v for k, v in r.items()} for r in rows)


def chart(name: str, rows: list[dict], args) -> None:
    """Per batch size: mark the model's Pareto fronts in ``rows`` (``pareto_<metric>`` columns) and write its chart,
    ``speed_accuracy_<model>_b<batch>.png``."""
    model = MODELS[name]
    for batch in sorted({r["batch"] for r in rows if r["model"] == name}, reverse=True):
        batch_rows = [r for r in rows if r["model"] == name and r["batch"] == batch]
        for metric in ERRORS[model.contact_free]:
            front = pareto(batch_rows, metric)
            for i, r in enumerate(batch_rows):
                r[f"pareto_{metric}"] = i in front
        plot_model(name, batch_rows, ERRORS[model.contact_free], model.frame_skip, batch, batch_rows[0]["threads"],
                   args.out / f"speed_accuracy_{name}_b{batch}.png")


def defaults_table(rows: list[dict]) -> str:
    """Markdown: per model and batch, torchsim's default point beside MuJoCo's (Euler at the model's timestep), their
    speed ratio, and whether torchsim's default is on each Pareto front (run ``chart`` first)."""
    lines = ["| model | batch | torchsim default: env-steps/s, errors | MuJoCo default: env-steps/s, errors | "
             "torchsim / MuJoCo speed | torchsim default on the front |", "|---|---|---|---|---|---|"]
    for name, model in MODELS.items():
        for batch in sorted({r["batch"] for r in rows if r["model"] == name}, reverse=True):
            found = {r["engine"]: r for r in rows if r["model"] == name and r["batch"] == batch and r["default"]}
            if len(found) < 2:
                continue
            ours, theirs = found["torchsim"], found["mujoco"]
            metrics = ERRORS[model.contact_free]

            def cell(r):
                return f"{r['env_steps_per_s']:,.0f}; " + ", ".join(f"{r[m]:.2g}" for m in metrics)

            front = ", ".join(f"{m}: {'yes' if ours.get(f'pareto_{m}') else 'no'}" for m in metrics)
            lines.append(f"| {name} | {batch} | {cell(ours)} | {cell(theirs)} | "
                         f"{ours['env_steps_per_s'] / theirs['env_steps_per_s']:.2f} | {front} |")
    return "\n".join(lines)


def parse_args():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", nargs="+", default=None, choices=list(MODELS), help="default: all (--quick: "
                   "pendulum and ant)")
    p.add_argument("--methods", nargs="+", default=None, choices=list(LOAD_OPTIONS),
                   help="with --dtypes: sweep these combinations instead of each model's settings")
    p.add_argument("--dtypes", nargs="+", default=None, choices=list(DTYPES))
    p.add_argument("--batches", type=int, nargs="+", default=[4096, 256], help="envs per timed step (one chart each)")
    p.add_argument("--threads", type=int, default=2, help="threads of both engines (torch's, mujoco.rollout's)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--eager", action="store_true", help="time torchsim eagerly (no compiles)")
    p.add_argument("--quick", action="store_true",
                   help="smoke run: pendulum and ant, spring float32 at the default substeps, MuJoCo Euler at its "
                        "timestep, eager, 1 repeat, written to /tmp/speed_accuracy unless --out is given")
    p.add_argument("--out", default=None, help="output folder (default: docs/)")
    p.add_argument("--merge", action="store_true",
                   help="keep the points of the CSV in --out that this run does not measure (charts show both)")
    p.add_argument("--no-mujoco", action="store_true", help="measure no MuJoCo points (with --merge: keep the CSV's)")
    p.add_argument("--replot", action="store_true",
                   help="measure nothing: recompute the Pareto fronts and charts of the CSV in --out")
    args = p.parse_args()
    args.models = args.models or (["pendulum", "ant"] if args.quick else list(MODELS))
    if args.quick:
        args.methods, args.dtypes, args.eager, args.repeats, args.batches = ["spring"], ["float32"], True, 1, [256]
    args.out = Path(args.out or ("/tmp/speed_accuracy" if args.quick else REPO / "docs"))
    return args


def main():
    args = parse_args()
    torch.set_num_threads(args.threads)
    allow_recompiles()
    args.out.mkdir(parents=True, exist_ok=True)
    csv_path = args.out / "speed_accuracy.csv"
    if args.replot:
        rows = read_csv(csv_path)
        for name in dict.fromkeys(r["model"] for r in rows):
            chart(name, rows, args)
        write_csv(rows, csv_path)
        log(defaults_table(rows))
        return
    log(f"torch {torch.__version__}, mujoco {mujoco.__version__}, {args.device}, {os.cpu_count()} cores, "
        f"{args.threads} threads, batches {args.batches}, {'eager' if args.eager else 'default strategy'}")
    start, rows = time.perf_counter(), read_csv(csv_path) if args.merge and csv_path.exists() else []
    for name in args.models:
        torch._dynamo.reset()  # each model compiles its own substep graphs
        counters.clear()
        model = MODELS[name]
        ref = mujoco_runs(model, REFERENCE_FACTOR)
        measured = [] if args.no_mujoco else mujoco_points(name, model, ref, args)
        settings = model.settings
        if args.methods or args.dtypes:
            settings = [(m, d) for m in args.methods or ["spring", "xpbd"] for d in args.dtypes or list(DTYPES)]
        for method, dtype in settings:
            measured += torchsim_points(name, model, ref, method, dtype, args)
        rows = merge(rows, measured)
        chart(name, rows, args)
        write_csv(rows, csv_path)  # after every model, so a stopped run keeps its rows
        log(f"{name} done at {(time.perf_counter() - start) / 60:.1f} min")
    minutes = (time.perf_counter() - start) / 60
    log(defaults_table(rows))
    log(f"wrote {args.out}/speed_accuracy.csv and {len(args.models)} charts in {minutes:.1f} min")


if __name__ == "__main__":
    main()
