"""The env models' comparison with MuJoCo that ``tests/test_models.py`` asserts and ``studies/check_models.py``
prints as a table: each model's start, open-loop actions and horizon, its MuJoCo and torchsim trajectories (float64,
eager), and the errors between them (trajectory, forward kinematics) and the distance travelled."""

import warnings
from pathlib import Path

import mujoco
import numpy as np
import torch

import torchsim
from models import quat_dist, random_q
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
