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
import time
import warnings
from pathlib import Path

import mujoco
import numpy as np
import torch

import torchsim
from torchsim.envs import ENVS

ASSETS = Path(__file__).resolve().parent.parent / "envs" / "assets"
F64 = torch.float64

# horizon [s]; kind: what is compared; seed: action seed; scale: control amplitude as a fraction of the ctrlrange.
# Frames per env step and substeps per model timestep are the env classes' (torchsim.envs.ENVS): the chosen ones.
_CHECKS = {
    "ant": dict(horizon=0.25, kind="root", seed=0),
    "hopper": dict(horizon=0.25, kind="root", seed=0),
    "walker2d": dict(horizon=0.25, kind="root", seed=0),
    "halfcheetah": dict(horizon=0.25, kind="root", seed=0),
    "reacher": dict(horizon=1.0, kind="q", seed=0, scale=0.1),
    "inverted_pendulum": dict(horizon=1.0, kind="q", seed=0, scale=0.1),
    "inverted_double_pendulum": dict(horizon=1.0, kind="q", seed=0, scale=0.02),
    "pusher": dict(horizon=1.0, kind="pusher", seed=0),
    "humanoid": dict(horizon=0.25, kind="root", seed=0),
}
MODELS = {name: dict(cfg, frames=ENVS[name].frame_skip, substeps=ENVS[name].substeps) for name, cfg in _CHECKS.items()}
PUSHER_ARM = slice(0, 7)
PUSHER_OBJECT = slice(7, 9)


def path(name: str) -> str:
    return str(ASSETS / f"{name}.xml")


def initial_q(m: mujoco.MjModel) -> np.ndarray:
    """Keyframe 'home' where the model has one, else qpos0 (the envs' reset centre)."""
    return m.key_qpos[0].copy() if m.nkey else m.qpos0.copy()


def initial_state(name: str, m: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
    """(q, qd) the trajectory starts from. Pusher: shoulder pan 0.4 and lift 0.4 rad put the wrist at the object's
    height, and the object sits 8 cm ahead of the wrist along the pan direction (object slides y, x), so the
    pan-driven sweep in ``actions`` pushes it within the horizon."""
    q, qd = initial_q(m), np.zeros(m.nv)
    if name == "pusher":
        q[0], q[1] = 0.4, 0.4
        q[7], q[8] = -0.0731, 0.2173
    return q, qd


def actions(name: str, m: mujoco.MjModel) -> np.ndarray:
    """(env steps, nu): fixed-seed uniform controls in the ctrlrange times the model's ``scale``, one row per env
    step (pusher: see below). The contact-free models use small controls so the comparison measures the dynamics,
    not limit impacts and chaos after a fall (reacher: 200 N m on armature 1 spins joint0 towards 200 rad/s)."""
    cfg = MODELS[name]
    steps = int(round(cfg["horizon"] / (m.opt.timestep * cfg["frames"])))
    lo, hi = m.actuator_ctrlrange.T
    acts = np.random.default_rng(cfg["seed"]).uniform(lo, hi, (steps, m.nu)) * cfg.get("scale", 1.0)
    if name == "pusher":  # full shoulder-pan torque sweeps the wrist into the object; the rest at 1/4 range
        acts[:, 1:] *= 0.25
        acts[:, 0] = hi[0]
    return acts


def mujoco_trajectory(m: mujoco.MjModel, q0, qd0, acts, frames: int):
    """MuJoCo trajectory of ``m`` as configured (timestep, integrator) from (q0, qd0), each row of ``acts`` held for
    ``frames`` steps: per row, (qpos, root xpos)."""
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = q0, qd0
    mujoco.mj_forward(m, d)
    qs, roots = [d.qpos.copy()], [d.xpos[1].copy()]
    for a in acts:
        d.ctrl[:] = a
        for _ in range(frames):
            mujoco.mj_step(m, d)
        qs.append(d.qpos.copy())
        roots.append(d.xpos[1].copy())
    return np.array(qs), np.array(roots)


def mujoco_rollout(name: str, factor: int = 1, acts=None):
    """MuJoCo trajectory at timestep / factor: per env step, (qpos, root xpos)."""
    m = mujoco.MjModel.from_xml_path(path(name))
    acts = actions(name, m) if acts is None else acts
    start = initial_state(name, m)
    m.opt.timestep /= factor
    return mujoco_trajectory(m, *start, acts, MODELS[name]["frames"] * factor)


def torchsim_rollout(name: str, substeps: int | None = None, method: str = "spring", acts=None, companions=False):
    """torchsim trajectory (float64, eager): per env step, (q, root xpos, diverged) of env 0, which runs ``acts``.

    With ``companions`` two more envs run alongside from the same start: zero controls, and full-range uniform
    random controls of another seed; ``diverged`` then covers all three (and requires finite q)."""
    m = mujoco.MjModel.from_xml_path(path(name))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sys = torchsim.load_mjcf(path(name), method=method, substeps=substeps, dtype=F64)
    acts = actions(name, m) if acts is None else acts
    batch = 3 if companions else 1
    q0, qd0 = initial_state(name, m)
    state = torchsim.init(sys, torch.tensor(np.tile(q0, (batch, 1))), torch.tensor(np.tile(qd0, (batch, 1))))
    lo, hi = m.actuator_ctrlrange.T
    other = np.random.default_rng(MODELS[name]["seed"] + 1).uniform(lo, hi, acts.shape)

    def root(s):
        return torchsim.mj_body_poses(sys, s.x_pos, s.x_quat)[0][0, 1].numpy().copy()

    qs, roots = [state.q[0].numpy().copy()], [root(state)]
    for a, b in zip(acts, other):
        ctrl = torch.tensor(np.stack([a, np.zeros_like(a), b])[:batch])
        for _ in range(MODELS[name]["frames"]):
            state = torchsim.step(sys, state, ctrl)
        qs.append(state.q[0].numpy().copy())
        roots.append(root(state))
    diverged = bool(state.diverged.any()) or not bool(torch.isfinite(state.q).all())
    return np.array(qs), np.array(roots), diverged


def trajectory_error(name: str, a, b) -> float:
    """The compared quantity's max difference between two rollouts (q, root) over the horizon."""
    kind = MODELS[name]["kind"]
    (qa, ra), (qb, rb) = a[:2], b[:2]
    if kind == "root":
        return float(np.abs(ra - rb).max())
    if kind == "pusher":
        return float(np.abs(qa[:, PUSHER_ARM] - qb[:, PUSHER_ARM]).max())
    return float(np.abs(qa - qb).max())


def joint_angle_error(name: str, a, b) -> float:
    """Max |angle difference| [rad] over the horizon of the hinges below the root body (the limbs' joints)."""
    m = mujoco.MjModel.from_xml_path(path(name))
    limb = [int(m.jnt_qposadr[j]) for j in range(m.njnt)
            if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE and m.jnt_bodyid[j] != 1]
    return float(np.abs(a[0][:, limb] - b[0][:, limb]).max()) if limb else float("nan")


def travel(name: str, rollout) -> float:
    """Root travel (contact envs) or the object's travel (pusher) over the horizon [m]; NaN for the others."""
    q, root = rollout[:2]
    kind = MODELS[name]["kind"]
    if kind == "root":
        return float(np.linalg.norm(root[-1] - root[0]))
    if kind == "pusher":
        return float(np.linalg.norm(q[-1, PUSHER_OBJECT] - q[0, PUSHER_OBJECT]))
    return float("nan")


def fk_error(name: str, batch: int = 16, seed: int = 1234) -> float:
    """Max |xpos| / quaternion (up to sign) difference of torchsim.init vs mj_forward for random q."""
    import sys as _sys

    _sys.path.insert(0, str(ASSETS.parent.parent / "tests"))
    from models import quat_dist, random_q

    m = mujoco.MjModel.from_xml_path(path(name))
    d = mujoco.MjData(m)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sys = torchsim.load_mjcf(path(name), dtype=F64)
    rng = np.random.default_rng(seed)
    q = random_q(m, batch, rng)
    state = torchsim.init(sys, torch.tensor(q), torch.tensor(rng.normal(size=(batch, m.nv))))
    xpos, xquat = torchsim.mj_body_poses(sys, state.x_pos, state.x_quat)
    err = 0.0
    for i in range(batch):
        d.qpos[:] = q[i]
        mujoco.mj_forward(m, d)
        err = max(err, float(np.abs(xpos[i].numpy() - d.xpos).max()),
                  float(quat_dist(xquat[i], torch.tensor(d.xquat)).max()))
    return err


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
