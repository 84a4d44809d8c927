"""Stability map: where each solution method fails, over the substep length h and a model parameter, and whether
the engine's divergence flag notices. See docs/stability.md for the reading.

    python studies/stability_map.py                   # the map -> docs/stability_map.csv, docs/stability_map.png
    python studies/stability_map.py --plot-only       # redraw the chart from the CSV
    python studies/stability_map.py --env-defaults --steps 10000   # every env at its defaults, random actions

Model (``chain_mjcf``): ``LINKS`` capsule links (0.5 m, 1 kg) hanging from the world on hinges about y; no contacts,
actuators, damping or limits: a passive, conservative system whose mechanical energy must not grow. The MJCF
timestep is one substep (``substeps=1``), float32 as in the envs. Chart panels (``PANELS``), h on the x axis:

- ``mass_ratio`` (both methods; xpbd also with 4 iterations): the links alternate 1 kg and r kg, so every joint
  links bodies of mass ratio r (mass and inertia scaled together).
- ``omega`` (both methods): MJCF joint ``stiffness`` on every hinge, as the natural frequency
  ``omega = sqrt(stiffness * w)`` [rad/s], ``w`` the dof's inverse inertia on its two bare links
  (``bare_dof_inverse_inertia``). Both methods apply passive springs as explicit torques on the bare links,
  which is stable only for ``omega h < 2``.
- ``kappa`` (spring only): the spring method's ``joint_stiffness`` fraction (``joint_damping`` stays 0.5).

A cell is ``SAMPLES`` envs started from random hinge angles U(-1, 1) rad (scaled down by ``omega / OMEGA_SWING``
where larger, so a stable stiff spring does not swing faster than a free link) and rates N(0, 1) rad/s, run for
``HORIZON_S``. An env's outcome is the first that applies: ``nonfinite`` (a non-finite state), ``energy``
(mechanical energy above its start by more than ``ENERGY_BOUND`` times the start's energy above rest),
``separation`` (a joint anchor gap above ``SEPARATION_BOUND_M``), else ``ok``; a cell shows its worst env. The run
itself has the bounds switched off; ``flagged`` counts the failing envs that the default flag (``load_mjcf``'s
``max_speed``/``max_distance``, judged by ``pipeline.contain_divergence`` after every step) would have caught.
"""

import argparse
import csv
import dataclasses
import sys
import textwrap
import time
import warnings
from pathlib import Path

import numpy as np
import torch

import torchsim
from torchsim import spatial
from torchsim.envs import ENVS, make
from torchsim.kinematics import anchor_gap
from torchsim.pipeline import contain_divergence, to_lanes_state

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))  # the chain, the env runs: tests share them
from stability_runs import (FLAG_BOUNDS, HORIZON_S, KAPPA_DEFAULT, SEPARATION_BOUND_M,  # noqa: E402
                            bare_dof_inverse_inertia, chain_system, env_default_run, initial_state,
                            substeps_per_env_step)

DOCS = Path(__file__).resolve().parent.parent / "docs"
SAMPLES = 4
H_GRID_S = (5e-4, 1e-3, 2e-3, 4e-3, 8e-3, 1.6e-2)
# Energy may not grow in a passive undamped chain; 10 % of the start's energy above rest is above the integrators'
# fluctuation (measured < 2 % in the stable cells without joint springs) and far below a blow-up (x 1e3 and more).
ENERGY_BOUND = 0.1
OUTCOMES = ("ok", "separation", "energy", "nonfinite")  # by severity
RATIOS = (1, 3, 10, 30, 100, 300, 1000)
OMEGAS = (10, 30, 100, 300, 1000, 3000, 10000)
KAPPAS = (0.05, 1, 2)  # and KAPPA_DEFAULT, a cell of the spring run


@dataclasses.dataclass(frozen=True)
class Run:
    """One batch per h: the envs of several cells share a System (mass ratio and joint springs vary per env;
    ``kappa`` and ``iterations`` are per System)."""

    method: str
    cells: tuple  # ((axis, value), ...)
    kappa: float = KAPPA_DEFAULT
    iterations: int = 1


_RATIO_CELLS = tuple(("mass_ratio", r) for r in RATIOS)
_OMEGA_CELLS = tuple(("omega", w) for w in OMEGAS)
RUNS = (Run("spring", _RATIO_CELLS + _OMEGA_CELLS + (("kappa", KAPPA_DEFAULT),)),
        Run("xpbd", _RATIO_CELLS + _OMEGA_CELLS), Run("xpbd", _RATIO_CELLS, iterations=4),
        *(Run("spring", (("kappa", k),), kappa=k) for k in KAPPAS))
PANELS = (("spring", 1, "mass_ratio"), ("xpbd", 1, "mass_ratio"), ("xpbd", 4, "mass_ratio"),
          ("spring", 1, "omega"), ("xpbd", 1, "omega"), ("spring", 1, "kappa"))  # (method, iterations, axis)
SHORT_NAME = {"ant": "ant", "halfcheetah": "cheetah", "humanoid": "humanoid", "reacher": "reacher", "hopper": "hopper",
              "walker2d": "walker", "inverted_pendulum": "ip", "inverted_double_pendulum": "idp", "pusher": "pusher",
              "ur5e_reach": "ur5e"}
AXIS_LABEL = {"mass_ratio": "mass ratio of linked bodies", "omega": "joint spring omega [rad/s]",
              "kappa": "spring joint_stiffness (kappa)"}


def joint_spring_omega(sys: torchsim.System) -> torch.Tensor:
    """``(B or 1, D)`` natural frequency [rad/s] of each dof's springs: MJCF stiffness plus position-servo gain
    (``-bias1 gear^2``), on the dof's bare links plus its armature (the spring method moves armature with the dof
    in its joint-space solve; on the chain, without armature or servos, this is the ``omega`` axis)."""
    servo = sys.dof_armature.new_zeros(sys.dof_armature.shape[-1]).index_add(0, sys.act_dof,
                                                                             -sys.act_bias[:, 1] * sys.act_gear ** 2)
    k = sys.dof_stiffness + servo
    return (k / (1 / bare_dof_inverse_inertia(sys) + sys.dof_armature)).sqrt()


def mechanical_energy(sys: torchsim.System, state: torchsim.State) -> torch.Tensor:
    """Kinetic + gravitational + joint-spring energy [J] per env ``(B,)``."""
    w_body = spatial.batch_first.quat_rotate_inv(state.x_quat, state.xd_ang)
    kinetic = 0.5 * (sys.body_mass * (state.xd_vel ** 2).sum(-1)).sum(-1) + 0.5 * (
        w_body * (sys.body_inertia @ w_body[..., None])[..., 0]).sum((-1, -2))
    gravity = -(sys.body_mass * (state.x_pos * sys.gravity).sum(-1)).sum(-1)
    stretch = state.q[:, sys.dof_qpos] - sys.dof_springref
    return kinetic + gravity + 0.5 * (sys.dof_stiffness * stretch ** 2).sum(-1)


def run_cells(sys: torchsim.System, state: torchsim.State, seconds: float) -> dict[str, torch.Tensor]:
    """Step the passive chain for ``seconds``; per env: outcome severity (index into OUTCOMES), the default flag's
    verdict, the largest energy growth (fraction of the start's energy above rest), anchor gap [m] and speed."""
    batch = state.q.shape[0]
    flag_sys = sys.replace(**FLAG_BOUNDS)
    rest = mechanical_energy(sys, torchsim.init(sys, torch.zeros_like(state.q), torch.zeros_like(state.qd)))
    start = mechanical_energy(sys, state)
    growth, gap, speed = (torch.zeros(batch) for _ in range(3))
    flagged = torch.zeros(batch, dtype=torch.bool)
    ctrl = torch.zeros(batch, sys.nu)
    for _ in range(round(seconds / sys.timestep)):
        state = torchsim.step(sys, state, ctrl)
        lanes_state = to_lanes_state(state)
        flagged |= contain_divergence(flag_sys, lanes_state, lanes_state).diverged
        growth = torch.maximum(growth, (mechanical_energy(sys, state) - start) / (start - rest))
        gap = torch.maximum(gap, anchor_gap(sys, state))
        speed = torch.maximum(speed, torch.maximum(state.xd_vel.abs().amax((1, 2)), state.xd_ang.abs().amax((1, 2))))
    # a non-finite env is frozen at its last finite state (state.diverged: the flag with the bounds switched off)
    severity = torch.where(state.diverged, 3, torch.where(growth > ENERGY_BOUND, 2, (gap > SEPARATION_BOUND_M).long()))
    return dict(severity=severity, flagged=flagged, growth=growth, gap=gap, speed=speed)


def sweep(run: Run, h_grid, seed: int = 0) -> list[dict]:
    """CSV rows of one run: one row per (h, cell)."""
    rows = []
    value = torch.tensor([float(v) for _, v in run.cells]).repeat_interleave(SAMPLES)

    def on(axis):
        return torch.tensor([name == axis for name, _ in run.cells]).repeat_interleave(SAMPLES)

    mass_ratio, omega = torch.where(on("mass_ratio"), value, 1.0), torch.where(on("omega"), value, 0.0)
    for h in h_grid:
        sys = chain_system(run.method, h, mass_ratio, omega, run.kappa, run.iterations)
        res = run_cells(sys, initial_state(sys, omega, torch.Generator().manual_seed(seed)), HORIZON_S)
        for i, (name, v) in enumerate(run.cells):
            cell = {k: t[i * SAMPLES:(i + 1) * SAMPLES] for k, t in res.items()}
            failed = cell["severity"] > 0
            rows.append(dict(
                method=run.method, iterations=run.iterations, axis=name, value=v, h_s=h,
                outcome=OUTCOMES[int(cell["severity"].max())], envs=SAMPLES, failed=int(failed.sum()),
                flagged=int((failed & cell["flagged"]).sum()), max_energy_growth=f"{cell['growth'].max():.3g}",
                max_gap_m=f"{cell['gap'].max():.3g}", max_speed_mps=f"{cell['speed'].max():.3g}"))
    return rows


def env_marks() -> list[dict]:
    """Each env's default substep h [s], largest mass ratio across a joint, stiffest joint spring or servo omega
    [rad/s] (``joint_spring_omega``)."""
    marks = []
    for name in ENVS:
        sys = make(name).sys
        linked = sys.jnt_parent < sys.num_bodies  # joints to the world have no mass ratio
        child, parent = sys.body_mass[sys.jnt_child[linked]], sys.body_mass[sys.jnt_parent[linked]]
        ratio = float(torch.maximum(child / parent, parent / child).max()) if linked.any() else 1.0
        omega = float(joint_spring_omega(sys).max()) if sys.nv else 0.0
        marks.append(dict(name=name, h=sys.substep_timestep, mass_ratio=ratio, omega=omega,
                          kappa=sys.joint_stiffness))
    return marks


def plot(rows: list[dict], marks: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    colours = ("#4caf50", "#ffb74d", "#e57373", "#7b1fa2")  # ok, separation, energy, nonfinite
    fig, axes = plt.subplots(2, 3, figsize=(16, 9.5), constrained_layout=True)
    for ax, (method, iterations, axis) in zip(axes.flat, PANELS):
        cells = [r for r in rows if (r["method"], int(r["iterations"]), r["axis"]) == (method, iterations, axis)]
        hs = sorted({float(r["h_s"]) for r in cells})
        values = sorted({float(r["value"]) for r in cells})
        grid = torch.full((len(values), len(hs)), float("nan"))
        for r in cells:
            i, j = values.index(float(r["value"])), hs.index(float(r["h_s"]))
            grid[i, j] = OUTCOMES.index(r["outcome"])
            if int(r["failed"]):
                missed = int(r["failed"]) - int(r["flagged"])
                ax.text(j, i, "flag" if not missed else f"miss {missed}/{r['failed']}", ha="center", va="center",
                        fontsize=7, color="white" if r["outcome"] == "nonfinite" else "black")
        ax.imshow(grid.numpy(), origin="lower", cmap=ListedColormap(colours), vmin=-0.5, vmax=3.5, aspect="auto")
        ax.set_xticks(range(len(hs)), [f"{h * 1e3:g}" for h in hs])
        ax.set_yticks(range(len(values)), [f"{v:g}" for v in values])
        ax.set_xlabel("substep h [ms]")
        ax.set_ylabel(AXIS_LABEL[axis])
        ax.set_title(f"{method}{f', {iterations} iterations' if iterations > 1 else ''}: h x {axis}")
        _mark_envs(ax, axis, marks, hs, values)
        if axis == "omega":
            ax.plot(range(len(hs)), [_index(2 / h, values) for h in hs], "k--", lw=1, label="omega h = 2")
            ax.legend(loc="lower right", fontsize=7)
    legend = [Patch(color=c, label=o) for c, o in zip(colours, OUTCOMES)]
    fig.legend(handles=legend, loc="outside lower center", ncols=4,
               title="cell = worst of its envs; 'flag': the divergence flag caught every failing env, "
                     "'miss k/n': it missed k of n; markers: the envs' defaults")
    fig.savefig(path, dpi=110)


def _index(x: float, grid: list) -> float:
    """Position of ``x`` in a chart's cell coordinates (log-interpolated between grid points, clamped to the grid)."""
    return float(np.interp(np.log(x), np.log(grid), np.arange(len(grid))))


def _mark_envs(ax, axis: str, marks: list[dict], hs: list, values: list) -> None:
    """Each env's default (h, value), by short name."""
    by_point = {}
    for mark in marks:
        value = mark[axis]
        if axis == "omega" and value == 0:
            continue  # no joint springs or servos in this env's model
        point = (_index(mark["h"], hs), _index(value, values))
        by_point.setdefault(point, []).append(SHORT_NAME.get(mark["name"], mark["name"]))
    for (x, y), names in by_point.items():
        ax.plot(x, y, "kx", ms=7)
        ax.annotate(textwrap.fill(", ".join(names), 20), (x, y), xytext=(4, 4), textcoords="offset points",
                    fontsize=6)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--plot-only", action="store_true", help="redraw the chart from the CSV")
    parser.add_argument("--env-defaults", action="store_true", help="run every env at its defaults instead")
    parser.add_argument("--steps", type=int, default=10000, help="env steps per env (--env-defaults)")
    parser.add_argument("--batch", type=int, default=2, help="envs per batch (--env-defaults)")
    parser.add_argument("--envs", nargs="+", default=list(ENVS), choices=list(ENVS))
    parser.add_argument("--out", type=Path, default=DOCS, help="folder for stability_map.csv/.png")
    args = parser.parse_args()
    torch.set_num_threads(1)
    warnings.simplefilter("ignore")  # the env models' ignored <sensor>s
    if args.env_defaults:
        for name in args.envs:
            t0 = time.perf_counter()
            res = env_default_run(name, args.steps, args.batch)
            print(f"{name:26s} {args.steps} env steps = {args.steps * substeps_per_env_step(name)} substeps x "
                  f"{args.batch} envs: diverged {res['diverged']}, finite {res['finite']}, anchor gap median "
                  f"{res['median_gap_m'] * 1e3:.2f} mm, max {res['max_gap_m'] * 1e3:.2f} mm "
                  f"({time.perf_counter() - t0:.0f} s)", flush=True)
        return
    csv_path = args.out / "stability_map.csv"
    if args.plot_only:
        with open(csv_path) as f:
            rows = list(csv.DictReader(f))
    else:
        rows = []
        for run in RUNS:
            t0 = time.perf_counter()
            rows += sweep(run, H_GRID_S)
            print(f"{run.method} kappa {run.kappa:g} iterations {run.iterations}: {len(run.cells)} cells x "
                  f"{len(H_GRID_S)} h done in {time.perf_counter() - t0:.0f} s", flush=True)
        with open(csv_path, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    plot(rows, env_marks(), args.out / "stability_map.png")
    print(f"wrote {csv_path} and {args.out / 'stability_map.png'}")


if __name__ == "__main__":
    main()
