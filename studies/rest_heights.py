"""Rest heights of the Ant and the Humanoid under zero control: torchsim's settled torso height against MuJoCo's
converged answer (MuJoCo at a fraction of the model's step), for the physics the envs use and the alternatives.

    python studies/rest_heights.py                  # every scene and physics (~3 min on 2 cores)
    python studies/rest_heights.py --scene ant      # one scene
    python studies/rest_heights.py --full           # torchsim settles from the scene's start too (~12 min)
    python studies/rest_heights.py --from-home      # the Ant from its home pose, 24 s (~4 min a row; with --full)
    python studies/rest_heights.py --substeps 40 80 # also the default physics at these substeps

Scenes:

* ``ant``: the shipped ``ant.xml``. From its ``home`` pose under zero control the ankles fold slowly (joint damping
  against the torso's weight) for ~15 s until every ankle meets its 30 deg limit, and it rests on the four lower-leg
  capsules' tips (MuJoCo: still 1.4e-2 m/s after 2 s, 0.3625 m and ~1e-9 m/s from 16 s on). So the scene starts
  there: ankles on their limits, hips 0, the feet 2 mm above the floor, and settles 3 s (``--from-home`` runs the
  whole fold instead; same heights to 0.01 mm).
* ``humanoid lying``: the shipped ``humanoid.xml`` has no rest under zero control: only its feet and shins collide,
  so it falls and its torso swings below the floor (MuJoCo: torso z -0.78 m and 0.7 m/s after 12 s). Here every
  geom collides with the floor (``contype="1"`` on the body geoms, as the standard Gym file has), and the humanoid
  starts on its back (pitched -90 deg about y, qpos0 joints, torso 0.1 m up) and settles 6 s: it rests on its back,
  head, arms and heels (9 contacts in MuJoCo).

MuJoCo settles each scene from its start at the model's step / ``--split`` (default 8), its converged answer: the
header line gives it against / 16 and against the model's own step. torchsim (float64, eager, one env, zero
control) then starts from MuJoCo's converged rest pose at rest and settles ``SETTLE_S``: the height it keeps there
is its rest height for the same resting configuration. ``--full`` settles torchsim from the scene's start instead,
as MuJoCo did (same heights to 0.04 mm for the spring rows; slower).

Measured (MuJoCo 4.0, torch 2.13 CPU; ``--float32 --substeps 40``; MuJoCo at dt/8, dt/16 and dt agree to 1e-6 m):

    model          | physics                               | torchsim    | MuJoCo dt/8 | MuJoCo dt   | diff [mm]
    ant            | spring/soft, 20 substeps (default)    | 0.36069     | 0.36248     | 0.36248     | -1.79
    ant            | spring/impulse, 20 substeps           | 0.36103     | 0.36248     | 0.36248     | -1.45
    ant            | xpbd/impulse, 20 substeps             | 0.34033     | 0.36248     | 0.36248     | -22.15 *
    ant            | spring/soft, 20 substeps, float32     | 0.36069     | 0.36248     | 0.36248     | -1.79
    ant            | spring/soft, 40 substeps              | 0.36195     | 0.36248     | 0.36248     | -0.53
    humanoid lying | spring/impulse, 6 substeps (default)  | 0.07712     | 0.07762     | 0.07762     | -0.51
    humanoid lying | spring/soft, 6 substeps               | 0.07698     | 0.07762     | 0.07762     | -0.64
    humanoid lying | xpbd/impulse, 6 substeps              | 0.07772     | 0.07762     | 0.07762     | +0.10
    humanoid lying | spring/impulse, 6 substeps, float32   | 0.07712     | 0.07762     | 0.07762     | -0.51
    humanoid lying | spring/impulse, 40 substeps           | 0.07763     | 0.07762     | 0.07762     | +0.00

    * not at rest: |qd| 2 m/s after 1 s (the other rows: < 2e-1 m/s, the humanoid's limbs creeping).

The Ant's gap: its contacts rest as deep as MuJoCo's (0.3414 vs 0.3415 mm per foot, each carrying 2.234 N); its
ankles sit 0.26 mrad past their limit against MuJoCo's 0.04 mrad (-0.1 mm); the rest, -1.7 mm, is the spring
method's joints giving under the torso's weight: forward kinematics of torchsim's own hinge angles puts the feet
2.03 mm into the floor where its bodies have them 0.34 mm in. That compliance goes as the substep squared (soft,
10 / 20 / 40 / 80 substeps: -6.87 / -1.79 / -0.53 / -0.21 mm) and as 1 / ``joint_stiffness`` (20 substeps, 0.2 /
0.4 / 0.8: -1.79 / -0.95 / -0.53 mm). The lying Humanoid's gap is the impulse contacts' Baumgarte rest depth
(0.5-0.7 mm at its loaded points against MuJoCo's 0.08-0.28 mm); its joints carry little load lying down.
"""

import argparse
import sys
import time
from pathlib import Path

import mujoco
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))  # the scenes the test asserts
from rest_scenes import F64, SCENES, ant_home, mujoco_rest, torchsim_rest  # noqa: E402

SETTLE_S = 1.0  # torchsim's settling from MuJoCo's rest pose [s]


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", choices=list(SCENES), action="append", help="default: every scene")
    parser.add_argument("--split", type=int, default=8, help="MuJoCo's converged answer at the model's dt / split")
    parser.add_argument("--from-home", action="store_true", help="the Ant from its home pose, 24 s")
    parser.add_argument("--full", action="store_true", help="torchsim settles from the scene's start, as MuJoCo")
    parser.add_argument("--substeps", type=int, nargs="*", default=[], help="also the default physics at these")
    parser.add_argument("--float32", action="store_true", help="also the default physics in float32 (the envs')")
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = []
    for name in args.scene or list(SCENES):
        make_xml, start, seconds, physics = SCENES[name]
        if name == "ant" and args.from_home:
            start, seconds, name = ant_home, 24.0, "ant from home"
        xml = make_xml()
        m = mujoco.MjModel.from_xml_string(xml)
        q0 = start(m)
        at_dt, mj_dt_v = mujoco_rest(xml, q0, seconds)
        mj_rest, mj_ref_v = mujoco_rest(xml, q0, seconds, args.split)
        fine, _ = mujoco_rest(xml, q0, seconds, 2 * args.split)
        mj_dt, mj_ref, mj_fine = float(at_dt[2]), float(mj_rest[2]), float(fine[2])
        print(f"{name}: dt {m.opt.timestep * 1e3:g} ms, {seconds:g} s from z {q0[2]:.4f}; MuJoCo dt/{args.split} "
              f"{mj_ref:.6f} m (|qvel| {mj_ref_v:.1e}), dt/{2 * args.split} {mj_fine:.6f} (converged to "
              f"{1e3 * abs(mj_fine - mj_ref):.3f} mm), dt {mj_dt:.6f} (|qvel| {mj_dt_v:.1e})", flush=True)
        runs = [(p, F64) for p in physics] + ([(physics[0], torch.float32)] if args.float32 else [])
        runs += [((*physics[0][:2], n), F64) for n in args.substeps]
        ts_start, ts_seconds = (q0, seconds) if args.full else (mj_rest, SETTLE_S)
        for (method, contact_model, substeps), dtype in runs:
            t0 = time.perf_counter()
            z, v, n = torchsim_rest(xml, ts_start, ts_seconds, method, contact_model, substeps, dtype)
            label = f"{method}/{contact_model}, {n} substeps" + (" (default)" if (method, contact_model, substeps)
                                                                  == physics[0] else "")
            label += ", f32" if dtype == torch.float32 else ""
            rows.append((name, label, z, mj_ref, mj_dt, 1e3 * (z - mj_ref), v))
            print(f"  {label}: {z:.6f} m (|qd| {v:.1e}), {time.perf_counter() - t0:.0f} s", flush=True)
    print(f"\ntorchsim settled {'from the scene start' if args.full else f'{SETTLE_S:g} s from MuJoCo rest pose'}")
    header = ("model", "physics", "torchsim [m]", f"MuJoCo dt/{args.split} [m]", "MuJoCo dt [m]", "diff [mm]",
              "torchsim |qd|")
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for name, label, z, ref, at_dt, diff, v in rows:
        print(f"| {name} | {label} | {z:.5f} | {ref:.5f} | {at_dt:.5f} | {diff:+.2f} | {v:.0e} |")


if __name__ == "__main__":
    main()
