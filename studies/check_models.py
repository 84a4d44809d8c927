"""Check the env models in envs/assets against MuJoCo: contact pairs, forward kinematics, and open-loop trajectories.

For every model it prints the contact-pair count, the pose error of ``torchsim.init`` vs MuJoCo's ``xpos``/``xquat``
(random q), and the trajectory agreement under the same open-loop actions (fixed-seed uniform random controls in
the ctrlrange, held for each env step of ``frames`` physics steps), float64, batch 1, eager:

- contact envs: the root body's position, max over the horizon of |x_torchsim - x_mujoco| [m], and the root's
  travel (final - initial position, norm) for each;
- contact-free envs (reacher, pendulums): max |q - q_mujoco| over the horizon [rad or m];
- pusher: max |q - q_mujoco| of the arm joints [rad], and the object's travel (it is pushed within the horizon);
- joint err: max |angle difference| of the limbs' hinges (below the root body) over the horizon [rad];
- ``mj dt/4``: the same errors between MuJoCo at the model's timestep and MuJoCo at a 4x smaller one (MuJoCo's own
  timestep sensitivity, for scale).

    python studies/check_models.py                          # all models, recommended substeps
    python studies/check_models.py --models hopper reacher --substeps 2 4 8
"""

import argparse
import sys
import time
import warnings
from pathlib import Path

import mujoco
import numpy as np
import torch

import torchsim

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))  # the rollouts and errors test_models asserts
from model_rollouts import (F64, MODELS, fk_error, initial_state, mujoco_rollout, path, torchsim_rollout,  # noqa: E402
                            trajectory_error, travel)


def joint_angle_error(name: str, a, b) -> float:
    """Max |angle difference| [rad] over the horizon of the hinges below the root body (the limbs' joints)."""
    m = mujoco.MjModel.from_xml_path(path(name))
    limb = [int(m.jnt_qposadr[j]) for j in range(m.njnt)
            if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE and m.jnt_bodyid[j] != 1]
    return float(np.abs(a[0][:, limb] - b[0][:, limb]).max()) if limb else float("nan")


def stability(name: str, substeps: int | None = None, seconds: float = 2.0, method: str = "spring") -> bool:
    """True if neither zero nor full-range random actions for ``seconds`` set ``state.diverged`` (batch 2)."""
    m = mujoco.MjModel.from_xml_path(path(name))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sys = torchsim.load_mjcf(path(name), method=method, substeps=substeps, dtype=F64)
    q0, qd0 = initial_state(name, m)
    state = torchsim.init(sys, torch.tensor(np.tile(q0, (2, 1))), torch.tensor(np.tile(qd0, (2, 1))))
    lo, hi = torch.tensor(m.actuator_ctrlrange.T)
    gen = torch.Generator().manual_seed(0)
    frames = MODELS[name]["frames"]
    for _ in range(int(round(seconds / (m.opt.timestep * frames)))):
        ctrl = torch.stack([torch.zeros(m.nu, dtype=F64), lo + (hi - lo) * torch.rand(m.nu, generator=gen, dtype=F64)])
        for _ in range(frames):
            state = torchsim.step(sys, state, ctrl)
    return not bool(state.diverged.any()) and bool(torch.isfinite(state.q).all())


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", nargs="+", default=list(MODELS), choices=list(MODELS))
    parser.add_argument("--substeps", nargs="+", type=int, default=None,
                        help="substep counts to try (default: each model's recommended count)")
    parser.add_argument("--method", default="spring", choices=["spring", "xpbd"])
    parser.add_argument("--stability", action="store_true", help="also run 2 s of zero and random actions")
    args = parser.parse_args()
    torch.set_num_threads(1)

    header = (f"{'model':26s} {'pairs':>5s} {'fk err':>8s} {'dt':>6s} {'sub':>4s} {'ts vs mj':>9s} {'mj dt/4':>9s} "
              f"{'joint err':>9s} {'mj dt/4':>8s} "
              f"{'travel ts':>9s} {'travel mj':>9s} {'s/step':>7s} {'stable':>6s}")
    print(header)
    for name in args.models:
        m = mujoco.MjModel.from_xml_path(path(name))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            pairs = torchsim.load_mjcf(path(name)).num_contact_pairs
        fk = fk_error(name)
        ref, ref4 = mujoco_rollout(name), mujoco_rollout(name, 4)
        mj_sens = trajectory_error(name, ref, ref4)
        for sub in args.substeps or [MODELS[name]["substeps"]]:
            t0 = time.perf_counter()
            ours = torchsim_rollout(name, sub, args.method)
            per_step = (time.perf_counter() - t0) / (len(ours[0]) - 1) / MODELS[name]["frames"]
            err = trajectory_error(name, ours, ref)
            stable = stability(name, sub, method=args.method) if args.stability else None
            print(f"{name:26s} {pairs:5d} {fk:8.1e} {m.opt.timestep:6.3f} {str(sub or 'def'):>4s} {err:9.2e} {mj_sens:9.2e} "
                  f"{joint_angle_error(name, ours, ref):9.3f} {joint_angle_error(name, ref4, ref):8.3f} "
                  f"{travel(name, ours):9.4f} {travel(name, ref):9.4f} {per_step:7.3f} "
                  f"{'-' if stable is None else ('yes' if stable else 'NO'):>6s}" + ("  DIVERGED" if ours[2] else ""),
                  flush=True)


if __name__ == "__main__":
    main()
