"""What the spring method's missing joint-space response costs: its joint solve (armature, damping, soft limits;
``joint_space.inertia_and_damping``) run once as it is and once with MuJoCo's articulated inverse inertia in its
place, on models whose passive rollouts miss MuJoCo where a limit stops a light link that carries a heavy one.

As it is, a dof impulse meets the inverse inertias of the dof's two bodies (``joint_space.hinge_rate_solve``'s
``A``; slides one at a time): a limit stops the light link alone and the heavy link it carries stretches the joint
spring between them and bounces back. The oracle solves every dof at once with ``A = M^-1``, ``M`` MuJoCo's
joint-space inertia of the rigid tree at the substep's coordinates (``mj_fullM``, armature taken out: it stays the
rotor element beside the bodies), and moves each body by its COM Jacobian times the dofs' rate change
(``mj_jac``): the response the articulation has with rigid joints, as MuJoCo's constraint solve sees it. The
rest of the step (springs, contacts) is unchanged. The oracle calls MuJoCo every substep, so it is a measurement,
not a method: it shows what building ``M`` in torchsim would buy (``docs/physics.md``, known limits).

Rollout and verdict quantities: ``studies/check_third_party.py``'s (qpos0, random velocities, 0.5 s; torchsim's
RMS error against MuJoCo at dt/4 over MuJoCo's own at dt). Models of hinges and slides only, one env, float64, eager.

    OMP_NUM_THREADS=1 python studies/articulated_limits.py                  # the chain, boxhead, spot_arm
    OMP_NUM_THREADS=1 python studies/articulated_limits.py --models chain   # one of them
"""

import argparse
import contextlib
import sys
import tempfile
import time
from pathlib import Path

import mujoco
import numpy as np
import torch

import torchsim
from check_third_party import HORIZON, SEED, VEL_STD, fetch, load, mujoco_rollout, q_error, torchsim_rollout
from torchsim import joint_space, lanes, spatial
from torchsim.kinematics import dof_values, joint_frames

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from test_soft_limits import light_link_carrying_a_heavy_one  # noqa: E402  (its strict xfail's model)

# name -> (package and version, or None for the chain; path inside the package)
MODELS = {
    "chain": (None, "a 0.1 kg link on a limited hinge carrying a 2 kg link (tests/test_soft_limits.py)"),
    "boxhead": (("dm_control", "1.0.50"), "dm_control/locomotion/soccer/assets/boxhead/boxhead.xml"),
    "spot_arm": (("robosuite", "1.5.2"), "robosuite/models/assets/robots/spot_arm/robot.xml"),
}


def articulated_joint_solve(m: mujoco.MjModel, system: torchsim.System):
    """A stand-in for ``joint_space.inertia_and_damping`` (same arguments and returns) solving every dof at once
    with ``A = M^-1`` (module docstring), for ``system`` loaded from ``m``."""
    d = mujoco.MjData(m)
    n = m.nv
    # a MuJoCo body of each torchsim body (jointless bodies are fused into their parents: any member moves alike)
    members = system.mjbody_body.tolist()
    bodies = [members.index(b) for b in range(system.num_bodies)]

    def solve(sys, before, after, frames, inv, h, q=None):
        d.qpos[:] = dof_values(sys, frames.q)[:, 0].numpy() + m.qpos0  # hinges and slides: q from the zero frame
        mujoco.mj_forward(m, d)
        inertia_matrix = np.zeros((n, n))
        mujoco.mj_fullM(m, d, inertia_matrix)
        a = torch.from_numpy(np.linalg.inv(inertia_matrix - np.diag(m.dof_armature)))[:, :, None]
        qd = dof_values(sys, frames.qd)
        # the dofs' rates after the substep's forces, at its start's poses
        qd_raw = dof_values(sys, joint_frames(sys, after._replace(x_pos=before.x_pos, x_quat=before.x_quat)).qd)
        armature = lanes.param(sys.dof_armature, 1).expand(n, 1)
        rotor = armature + h * lanes.param(sys.dof_damping, 1).expand(n, 1)
        a_flat = a.reshape(n * n, 1)
        mat, rhs = joint_space._dof_system(a_flat, rotor, armature * qd, qd_raw)
        if sys.dof_limits and q is not None:
            limits = joint_space.limit_rows(sys, q, qd, h)
            mat, rhs = joint_space._limit_system(a_flat, a, rotor, armature * qd, qd_raw, spatial.spd_solve(mat, rhs),
                                                 limits)
        rate_change = a[:, :, 0] @ spatial.spd_solve(mat, rhs)[:, 0]
        vel, ang = after.xd_vel.clone(), after.xd_ang.clone()
        jac_lin, jac_ang = np.zeros((3, n)), np.zeros((3, n))
        for b, body in enumerate(bodies):  # at the torchsim body's COM, where its velocity is held
            mujoco.mj_jac(m, d, jac_lin, jac_ang, before.x_pos[:, b, 0].numpy(), body)
            vel[:, b, 0] += torch.from_numpy(jac_lin) @ rate_change
            ang[:, b, 0] += torch.from_numpy(jac_ang) @ rate_change
        return after._replace(xd_vel=vel, xd_ang=ang), qd_raw + rate_change[:, None]

    return solve


@contextlib.contextmanager
def joint_solve(solve):
    """``joint_space.inertia_and_damping`` replaced by ``solve`` inside the block (the spring method calls it
    through the module)."""
    original = joint_space.inertia_and_damping
    joint_space.inertia_and_damping = solve
    try:
        yield
    finally:
        joint_space.inertia_and_damping = original


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
    print("| model | substeps | MuJoCo dt vs dt/4 | torchsim, as it is | ratio | with M^-1 (oracle) | ratio |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    with tempfile.TemporaryDirectory() as scratch:
        for name in args.models:
            path = model_path(name, args.cache, Path(scratch))
            m = torchsim.io_mjcf.mujoco_model(path, 64)
            if not set(m.jnt_type.tolist()) <= {mujoco.mjtJoint.mjJNT_SLIDE, mujoco.mjtJoint.mjJNT_HINGE}:
                raise ValueError(f"{name}: the oracle takes hinges and slides only")
            _, system, _ = load(path, max_hull_vertices=64)
            steps = round(HORIZON / m.opt.timestep)
            qd0 = np.random.default_rng(SEED).normal(0.0, VEL_STD, m.nv)
            fine_model = torchsim.io_mjcf.mujoco_model(path, 64)
            fine_model.opt.timestep /= 4
            fine, _ = mujoco_rollout(fine_model, qd0, steps, 4)
            mj = q_error(m, mujoco_rollout(m, qd0, steps, 1)[0], fine)
            errors = []
            for solve in (joint_space.inertia_and_damping, articulated_joint_solve(m, system)):
                t0 = time.perf_counter()
                with joint_solve(solve):
                    ours, diverged = torchsim_rollout(system, m, qd0, steps, float("inf"))
                errors.append(float("nan") if diverged else q_error(m, ours, fine))
                print(f"  {name}: RMS error {errors[-1]:.3e} in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
            print(f"| {name} | {system.substeps} | {mj:.2e} | {errors[0]:.2e} | {errors[0] / mj:.2f} | {errors[1]:.2e} | "
                  f"{errors[1] / mj:.2f} |", flush=True)


if __name__ == "__main__":
    main()
