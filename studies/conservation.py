"""Conservation against the time step: drift of linear momentum, angular momentum and energy for torchsim's two
methods and MuJoCo's Euler, RK4 and implicitfast integrators on the same conservative scenes.

    OMP_NUM_THREADS=1 python studies/conservation.py            # sweep -> docs/conservation.csv, docs/conservation.png
    python studies/conservation.py --replot                     # redraw the chart from the CSV

Scenes (``SCENES``; no contacts, actuators, damping, limits or joint springs):

- ``chain``: a free-floating chain of four capsule links (different radii, so different masses; hinges about y, z,
  (1, 0, 1) and x) in zero gravity, from a random root orientation and hinge angles, random hinge rates and a random
  root twist. Linear momentum, angular momentum about the centre of mass and kinetic energy are all conserved.
- ``dzhanibekov``: one asymmetric free body (principal moments 0.1, 0.2, 0.3 kg m^2, inertial frame turned against
  the body frame) in zero gravity, spun at 10 rad/s about its intermediate axis with a 1 % perturbation: it flips
  over about every 1.6 s (the tennis-racket effect). Angular momentum and kinetic energy are conserved.
- ``pendulum``: three capsule links hanging from the world on hinges about y, x and y (a 3D chain) under gravity,
  from random angles U(-1, 1) rad and rates N(0, 1) rad/s. Mechanical energy is conserved (momentum is not).

Each point: ``SAMPLES`` random starts of one scene for ``HORIZON_S`` s at one time step ``h``: torchsim in float64
with one substep per step (``substeps=1``, MJCF timestep = h; the default divergence flag on), eager
``torchsim.step``; MuJoCo 4.0 with the integrator set, the same MJCF. The quantities are taken from the bodies'
poses and velocities in the world frame after every step, by the same code for both engines (``quantities``; for
MuJoCo from ``xipos``/``ximat``/``cvel``, checked against ``subtree_linvel``/``subtree_angmom``/``energy`` and
against torchsim at t = 0 to 1e-9). Drift = max over the horizon and the starts of ``|Q(t) - Q(0)| / scale``:

- linear momentum P: scale ``sqrt(2 M T0)`` (the momentum of the total mass M moving with the start's kinetic
  energy T0);
- angular momentum L about the system's centre of mass: scale ``|L(0)|``;
- energy E (kinetic + gravitational): scale ``E(0) - E_rest``, the start's energy above the scene's rest pose
  (T0 in zero gravity); ``energy_final``: the signed change at the end, (E(T) - E(0)) / scale, mean of the starts.

``anchor_gap_m`` (torchsim): the largest joint-anchor separation seen (``torchsim.kinematics.anchor_gap``); the
energy in the stretched joints is not counted in E. A run is marked diverged when torchsim's divergence flag is set
or a quantity turns non-finite; its drift is then drawn at the chart's ceiling.
"""

import argparse
import csv
import math
import os
import sys
import time
from pathlib import Path

import mujoco
import numpy as np
import torch

import torchsim
from torchsim.kinematics import anchor_gap

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))  # the scenes and measures tests share
from conservation_scenes import (QUANTITIES, SAMPLES, SCENES, Scene, check_start, drifts, load,  # noqa: E402
                                 mujoco_quantities, rest_energy, starts, torchsim_quantities)

DOCS = Path(__file__).resolve().parent.parent / "docs"
H_GRID_S = (5e-4, 1e-3, 2e-3, 4e-3, 8e-3, 1.6e-2)
HORIZON_S = 2.0
TORCHSIM_METHODS = ("spring", "xpbd")
MUJOCO_INTEGRATORS = {"Euler": mujoco.mjtIntegrator.mjINT_EULER, "RK4": mujoco.mjtIntegrator.mjINT_RK4,
                      "implicitfast": mujoco.mjtIntegrator.mjINT_IMPLICITFAST}
METHODS = (*TORCHSIM_METHODS, *MUJOCO_INTEGRATORS)
FLOOR = 1e-16  # drifts below this (exact to rounding) are drawn here
CEILING = 1e2  # diverged runs are drawn here


def log(msg: str) -> None:
    print(msg, flush=True)


def mujoco_run(scene: Scene, h: float, integrator: str) -> tuple[dict, bool]:
    m = mujoco.MjModel.from_xml_string(scene.mjcf(h))
    m.opt.integrator = MUJOCO_INTEGRATORS[integrator]
    d = mujoco.MjData(m)
    qpos, qvel = starts(scene, m)
    steps = round(HORIZON_S / h)
    runs = []
    for b in range(SAMPLES):
        mujoco.mj_resetData(m, d)
        d.qpos[:], d.qvel[:] = qpos[b], qvel[b]
        mujoco.mj_forward(m, d)
        series = [mujoco_quantities(m, d)]
        for _ in range(steps):
            mujoco.mj_step(m, d)
            mujoco.mj_forward(m, d)  # poses and velocities of the new state
            series.append(mujoco_quantities(m, d))
        runs.append({k: np.stack([s[k] for s in series]) for k in series[0]})
    series = {k: np.stack([r[k] for r in runs], 1) for k in runs[0]}
    out = drifts(series, scene, m.body_mass.sum(), rest_energy(scene, m))
    return out, not all(np.isfinite(v) for v in out.values())


def torchsim_run(scene: Scene, h: float, method: str) -> tuple[dict, bool]:
    sys = load(scene, h, method)
    m = mujoco.MjModel.from_xml_string(scene.mjcf(h))
    qpos, qvel = (torch.tensor(x, dtype=torch.float64) for x in starts(scene, m))
    state = torchsim.init(sys, qpos, qvel)
    ctrl = torch.zeros(SAMPLES, sys.nu, dtype=torch.float64)
    history = [state]
    for _ in range(round(HORIZON_S / h)):
        state = torchsim.step(sys, state, ctrl)
        history.append(state)
    series = torchsim_quantities(sys, *(torch.stack(x) for x in list(zip(*history))[:4]))
    out = drifts(series, scene, float(sys.body_mass.sum()), rest_energy(scene, m))
    if (m.jnt_type != mujoco.mjtJoint.mjJNT_FREE).any():  # joints between bodies
        out["anchor_gap_m"] = float(anchor_gap(sys, torchsim.State(*(torch.cat(x) for x in zip(*history)))).max())
    return out, bool(state.diverged.any()) or not all(np.isfinite(v) for v in out.values())


def sweep(scenes, methods) -> list[dict]:
    rows = []
    for name in scenes:
        scene = SCENES[name]
        gap = check_start(scene)
        log(f"{name}: torchsim vs MuJoCo quantities at t = 0 agree to {gap:.1e} (relative)")
        assert gap < 1e-9, f"{name}: quantities disagree at t = 0 by {gap:.2e}"
        for method in methods:
            for h in H_GRID_S:
                t0 = time.perf_counter()
                if method in TORCHSIM_METHODS:
                    out, diverged = torchsim_run(scene, h, method)
                else:
                    out, diverged = mujoco_run(scene, h, method)
                rows.append(dict(scene=name, method=method, engine="torchsim" if method in TORCHSIM_METHODS
                                 else "mujoco", h_s=h, horizon_s=HORIZON_S, samples=SAMPLES, diverged=diverged,
                                 **{k: out.get(k, "") for k in QUANTITIES}, energy_final=out["energy_final"],
                                 anchor_gap_m=out.get("anchor_gap_m", "")))
                log(f"{name:>12} {method:>12} h {h * 1e3:6.2f} ms: " + ", ".join(
                    f"{k} {v:.2e}" for k, v in out.items()) + ("  DIVERGED" if diverged else "")
                    + f"  ({time.perf_counter() - t0:.1f} s)")
    return rows


def write_csv(rows: list[dict], path: Path) -> None:
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, list(rows[0]))
        writer.writeheader()
        writer.writerows({k: f"{v:.4g}" if isinstance(v, float) else v for k, v in r.items()} for r in rows)


def read_csv(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    for r in rows:
        r["h_s"] = float(r["h_s"])
        r["diverged"] = r["diverged"] == "True"
        for k in QUANTITIES:
            r[k] = float(r[k]) if r[k] != "" else None
        r["energy_final"] = float(r["energy_final"])
        r["anchor_gap_m"] = float(r["anchor_gap_m"]) if r.get("anchor_gap_m", "") != "" else None
    return rows


def slope(rows: list[dict], scene: str, method: str, quantity: str, h_max: float = 4e-3) -> float:
    """Least-squares slope of log drift against log h over the undiverged points with h <= ``h_max`` above FLOOR."""
    pts = [(r["h_s"], r[quantity]) for r in rows if (r["scene"], r["method"]) == (scene, method)
           and not r["diverged"] and r[quantity] is not None and FLOOR < r[quantity] < CEILING and r["h_s"] <= h_max]
    if len(pts) < 3 or max(q for _, q in pts) < 1e-10:  # fewer than 3 points, or rounding only
        return math.nan
    h, q = np.log(np.array(pts)).T
    return float(np.polyfit(h, q, 1)[0])


def summary(rows: list[dict], h: float = 1e-3) -> None:
    """Print, per scene and conserved quantity, each method's drift at ``h`` with its slope (``slope``), the signed
    energy change at the end, and torchsim's largest anchor gap per h (the docs' table)."""
    methods = list(dict.fromkeys(r["method"] for r in rows))
    at = {(r["scene"], r["method"]): r for r in rows if abs(r["h_s"] - h) < 1e-12}
    log(f"| at h = {h * 1e3:g} ms: drift (slope) | " + " | ".join(methods) + " |")
    for scene in dict.fromkeys(r["scene"] for r in rows):
        for k in (*SCENES[scene].conserved, "energy_final"):
            cells = []
            for method in methods:
                r = at.get((scene, method))
                if r is None:
                    cells.append("-")
                elif k == "energy_final":
                    cells.append(f"{r[k]:+.1e}")
                else:
                    order = slope(rows, scene, method, k)
                    cells.append(f"{r[k]:.1e} ({order:.1f})" if math.isfinite(order) else f"{r[k]:.1e} (rounding)")
            log(f"| {scene}, {k} | " + " | ".join(cells) + " |")
    for r in rows:
        if r["anchor_gap_m"] is not None and r["h_s"] >= 4e-3:
            log(f"anchor gap {r['scene']} {r['method']} h {r['h_s'] * 1e3:g} ms: {r['anchor_gap_m'] * 1e3:.2g} mm")


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colours = dict(spring="tab:blue", xpbd="tab:orange", Euler="tab:green", RK4="tab:red", implicitfast="tab:purple")
    styles = dict(chain=("-", "o"), dzhanibekov=("--", "s"), pendulum=(":", "^"))
    titles = dict(linear_momentum="linear momentum  |P(t) - P(0)| / sqrt(2 M T0)",
                  angular_momentum="angular momentum about COM  |L(t) - L(0)| / |L(0)|",
                  energy="energy  |E(t) - E(0)| / (E(0) - E_rest)")
    fig, axes = plt.subplots(1, 3, figsize=(17, 5.8), constrained_layout=True)
    for ax, quantity in zip(axes, QUANTITIES):
        for scene in styles:
            for method in colours:
                pts = [r for r in rows if (r["scene"], r["method"]) == (scene, method) and r[quantity] is not None]
                if not pts:
                    continue
                h = np.array([r["h_s"] for r in pts]) * 1e3
                y = np.array([CEILING if r["diverged"] else min(max(r[quantity], FLOOR), CEILING) for r in pts])
                ls, marker = styles[scene]
                wide = method in ("spring", "Euler")  # under the lines that can coincide with them
                ax.plot(h, y, ls=ls, marker=marker, ms=6 if wide else 4, color=colours[method], lw=4 if wide else 1.5,
                        alpha=0.55 if wide else 1.0, label=f"{method}, {scene}")
                bad = np.array([r["diverged"] for r in pts])
                if bad.any():
                    ax.plot(h[bad], y[bad], "x", color="k", ms=9, mew=2)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_ylim(FLOOR / 3, CEILING * 3)
        ax.set_xlabel("time step h [ms] (torchsim: 1 substep per step)")
        ax.set_title(titles[quantity], fontsize=10)
        ax.grid(True, which="major", alpha=0.3)
    from matplotlib.lines import Line2D

    wide = ("spring", "Euler")
    handles = [Line2D([], [], color=c, lw=4 if m in wide else 1.5, alpha=0.55 if m in wide else 1.0,
                      label=("torchsim " if m in TORCHSIM_METHODS else "MuJoCo ") + m) for m, c in colours.items()]
    handles += [Line2D([], [], color="grey", ls=ls, marker=mk, label=f"scene: {scene}")
                for scene, (ls, mk) in styles.items()]
    fig.legend(handles=handles, loc="outside lower center", ncols=len(handles), fontsize=9)
    fig.suptitle(f"Drift over {HORIZON_S:g} s (max over time and {SAMPLES} random starts), float64; "
                 f"black x: diverged (drawn at {CEILING:g}); at {FLOOR:g}: exact to rounding\n"
                 "lines that coincide: MuJoCo Euler and implicitfast on chain and pendulum (no damping: the same "
                 "step); torchsim spring and xpbd on dzhanibekov (one body: the same integrator), and their angular "
                 "momentum with implicitfast's", fontsize=10)
    fig.savefig(path, dpi=100)


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    p.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS))
    p.add_argument("--out", default=str(DOCS), help="folder for conservation.csv and conservation.png")
    p.add_argument("--replot", action="store_true", help="measure nothing: redraw the chart from the CSV")
    args = p.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(1)
    if not args.replot:
        log(f"torch {torch.__version__}, mujoco {mujoco.__version__}, {os.cpu_count()} cores, 1 thread; "
            f"{HORIZON_S:g} s, {SAMPLES} starts per point")
        t0 = time.perf_counter()
        write_csv(sweep(args.scenes, args.methods), out / "conservation.csv")
        log(f"swept in {time.perf_counter() - t0:.0f} s")
    rows = read_csv(out / "conservation.csv")
    summary(rows)
    plot(rows, out / "conservation.png")
    log(f"wrote {out / 'conservation.csv'} and {out / 'conservation.png'}")


if __name__ == "__main__":
    main()
