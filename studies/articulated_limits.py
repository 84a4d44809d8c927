"""What the spring method's missing joint-space response costs: passive rollouts on its default model and on the
articulated model (``contact_model="articulated"``, ``torchsim.tree_solve``), for models that miss MuJoCo where a
limit stops a light link that carries a heavy one.

On the default model a dof impulse meets the inverse inertias of the dof's two bodies
(``joint_space.hinge_rate_solve``'s ``A``; slides one at a time): a limit stops the light link alone and the heavy
link it carries stretches the joint spring between them and bounces back. The articulated model solves every dof
at once through ``M^-1``, ``M`` the joint-space inertia of the rigid tree at the substep's start
(``torchsim.articulation``, equal to MuJoCo's ``mj_fullM`` less armature: ``tests/test_articulation.py``), with
the joints held at the velocity level: the response the articulation has with rigid joints, as MuJoCo's
constraint solve sees it.

Rollout and verdict quantities: ``studies/check_third_party.py``'s (qpos0, random velocities, 0.5 s; torchsim's
RMS error against MuJoCo at dt/4 over MuJoCo's own at dt). One env, float64, eager.

    OMP_NUM_THREADS=1 python studies/articulated_limits.py                  # the chain, boxhead, spot_arm
    OMP_NUM_THREADS=1 python studies/articulated_limits.py --models chain   # one of them
"""

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

import torchsim
from check_third_party import HORIZON, SEED, VEL_STD, fetch, load, mujoco_rollout, q_error, torchsim_rollout

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from test_soft_limits import light_link_carrying_a_heavy_one  # noqa: E402  (its strict xfail's model)

# name -> (package and version, or None for the chain; path inside the package)
MODELS = {
    "chain": (None, "a 0.1 kg link on a limited hinge carrying a 2 kg link (tests/test_soft_limits.py)"),
    "boxhead": (("dm_control", "1.0.50"), "dm_control/locomotion/soccer/assets/boxhead/boxhead.xml"),
    "spot_arm": (("robosuite", "1.5.2"), "robosuite/models/assets/robots/spot_arm/robot.xml"),
}


def model_path(name: str, cache: Path, scratch: Path) -> Path:
    package, inside = MODELS[name]
    if package is None:
        path = scratch / "chain.xml"
        path.write_text(light_link_carrying_a_heavy_one(0.1))
        return path
    return fetch(cache, *package) / inside


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", nargs="+", default=list(MODELS), choices=list(MODELS))
    parser.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "torchsim" / "third_party")
    args = parser.parse_args()
    torch.set_num_threads(1)
    print("| model | substeps | MuJoCo dt vs dt/4 | torchsim, default | ratio | articulated | ratio |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    with tempfile.TemporaryDirectory() as scratch:
        for name in args.models:
            path = model_path(name, args.cache, Path(scratch))
            m = torchsim.io_mjcf.mujoco_model(path, 64)
            steps = round(HORIZON / m.opt.timestep)
            qd0 = np.random.default_rng(SEED).normal(0.0, VEL_STD, m.nv)
            fine_model = torchsim.io_mjcf.mujoco_model(path, 64)
            fine_model.opt.timestep /= 4
            fine, _ = mujoco_rollout(fine_model, qd0, steps, 4)
            mj = q_error(m, mujoco_rollout(m, qd0, steps, 1)[0], fine)
            errors = []
            for contact_model in ("impulse", "articulated"):
                t0 = time.perf_counter()
                _, system, _ = load(path, max_hull_vertices=64, contact_model=contact_model)
                ours, diverged = torchsim_rollout(system, m, qd0, steps, float("inf"))
                errors.append(float("nan") if diverged else q_error(m, ours, fine))
                print(f"  {name}: RMS error {errors[-1]:.3e} in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
            print(f"| {name} | {system.substeps} | {mj:.2e} | {errors[0]:.2e} | {errors[0] / mj:.2f} | {errors[1]:.2e} | "
                  f"{errors[1] / mj:.2f} |", flush=True)


if __name__ == "__main__":
    main()
