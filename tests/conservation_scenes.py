"""The conservative scenes of docs/conservation.md and their measures, shared by ``tests/test_conservation.py`` and
``studies/conservation.py`` (whose docstring describes the scenes, the quantities and the drift): each scene's MJCF
and random starts, the momenta and energy of bodies computed by the same code for torchsim and MuJoCo, and their
drift over a run."""

import dataclasses
import math

import mujoco
import numpy as np
import torch

import torchsim

SAMPLES = 3
QUANTITIES = ("linear_momentum", "angular_momentum", "energy")
_OFF = 'contype="0" conaffinity="0"'


@dataclasses.dataclass(frozen=True)
class Scene:
    body: str  # the <worldbody> content
    gravity: bool
    conserved: tuple  # the QUANTITIES the scene conserves
    start: callable  # (MjModel, np.random.Generator) -> (qpos, qvel)

    def mjcf(self, h: float) -> str:
        gravity = "" if self.gravity else ' gravity="0 0 0"'
        return (f'<mujoco><option timestep="{h}"{gravity}><flag contact="disable"/></option>'
                f'<worldbody>{self.body}</worldbody></mujoco>')


def _chain_body() -> str:
    links = [("0 0 0", "0.06"), ("0.4 0 0", "0.04"), ("0.4 0 0", "0.05"), ("0.4 0 0", "0.03")]
    axes = ("0 1 0", "0 0 1", "1 0 1", "1 0 0")
    body = ""
    for i in reversed(range(len(links))):
        pos, radius = links[i]
        joint = '<freejoint/>' if i == 0 else f'<joint type="hinge" axis="{axes[i]}"/>'
        body = (f'<body name="link{i}" pos="{pos}">{joint}<geom type="capsule" fromto="0 0 0 0.4 0 0" '
                f'size="{radius}" {_OFF}/>{body}</body>')
    return body


def _random_quat(rng) -> np.ndarray:
    q = rng.normal(size=4)
    return q / np.linalg.norm(q)


def _chain_start(m, rng):
    qpos, qvel = m.qpos0.copy(), np.zeros(m.nv)
    qpos[3:7] = _random_quat(rng)
    qpos[7:] = rng.uniform(-0.5, 0.5, m.nq - 7)
    qvel[:3] = rng.normal(0, 0.3, 3)  # root linear velocity (world frame)
    qvel[3:6] = rng.normal(0, 1.0, 3)  # root angular velocity (body frame, MuJoCo's free joint)
    qvel[6:] = rng.normal(0, 2.0, m.nv - 6)
    return qpos, qvel


DZ_MOMENTS = (0.1, 0.2, 0.3)
DZ_IQUAT = (0.9, 0.3, -0.2, 0.25)  # inertial frame against the body frame (normalised by MuJoCo)
DZ_SPIN = 10.0  # rad/s


def _dzhanibekov_start(m, rng):
    qpos, qvel = m.qpos0.copy(), np.zeros(m.nv)
    qpos[3:7] = _random_quat(rng)
    inertial = rng.normal(0, 0.01, 3)
    inertial[1] = 1.0  # about the intermediate axis, 1 % off
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, m.body_iquat[1])
    qvel[3:6] = DZ_SPIN * rot.reshape(3, 3) @ inertial  # body frame
    return qpos, qvel


def _pendulum_body() -> str:
    axes = ("0 1 0", "1 0 0", "0 1 0")
    body = ""
    for i in reversed(range(len(axes))):
        body = (f'<body name="link{i}" pos="0 0 {-0.5 if i else 0}"><joint type="hinge" axis="{axes[i]}"/>'
                f'<geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.04" {_OFF}/>{body}</body>')
    return body


def _pendulum_start(m, rng):
    return rng.uniform(-1, 1, m.nq), rng.normal(0, 1, m.nv)


SCENES = {
    "chain": Scene(_chain_body(), False, QUANTITIES, _chain_start),
    "dzhanibekov": Scene(f'<body name="rotor"><freejoint/><inertial pos="0.05 -0.02 0.03" quat="'
                         f'{" ".join(map(str, DZ_IQUAT))}" mass="2" diaginertia="{" ".join(map(str, DZ_MOMENTS))}"/>'
                         f'<geom type="sphere" size="0.1" {_OFF} mass="0"/></body>', False,
                         ("angular_momentum", "energy"), _dzhanibekov_start),
    "pendulum": Scene(_pendulum_body(), True, ("energy",), _pendulum_start),
}


def quantities(mass, pos, rot, inertia, vel, ang, gravity) -> dict:
    """Linear momentum ``(..., 3)``, angular momentum about the system's COM ``(..., 3)`` and energy ``(...,)``
    (kinetic + gravitational) of bodies with masses ``mass (N,)``, COM positions ``pos (..., N, 3)``, frame rotations
    ``rot (..., N, 3, 3)`` (body to world), inertias about the COM in that frame ``inertia (N, 3, 3)``, COM velocities
    ``vel`` and angular velocities ``ang (..., N, 3)`` (world frame), under ``gravity (3,)``."""
    m = mass[:, None]
    momentum = (m * vel).sum(-2)
    com = (m * pos).sum(-2, keepdims=True) / mass.sum()
    ang_body = np.einsum("...ji,...j->...i", rot, ang)
    spin_body = np.einsum("nij,...nj->...ni", inertia, ang_body)
    spin = np.einsum("...ij,...j->...i", rot, spin_body)
    angular = (np.cross(pos - com, m * vel) + spin).sum(-2)
    kinetic = 0.5 * (m * vel ** 2).sum((-1, -2)) + 0.5 * (ang_body * spin_body).sum((-1, -2))
    potential = -(m * pos * gravity).sum((-1, -2))
    return dict(linear_momentum=momentum, angular_momentum=angular, energy=kinetic + potential, kinetic=kinetic)


def _quat_mat(q: np.ndarray) -> np.ndarray:
    """``(..., 3, 3)`` rotation matrices of unit quaternions ``(..., 4)`` (wxyz)."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                     2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                     2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1).reshape(q.shape[:-1]
                                                                                                       + (3, 3))


def torchsim_quantities(sys: torchsim.System, x_pos, x_quat, xd_vel, xd_ang) -> dict:
    """``quantities`` of torchsim states (batch-first tensors, any leading dims)."""
    n = lambda t: t.detach().double().cpu().numpy()  # noqa: E731
    return quantities(n(sys.body_mass), n(x_pos), _quat_mat(n(x_quat)), n(sys.body_inertia), n(xd_vel), n(xd_ang),
                      n(sys.gravity))


def mujoco_quantities(m: mujoco.MjModel, d: mujoco.MjData) -> dict:
    """``quantities`` of MuJoCo's bodies after ``mj_forward`` (world body left out)."""
    root_com = d.subtree_com[m.body_rootid[1:]]
    ang, lin = d.cvel[1:, :3], d.cvel[1:, 3:]  # about subtree_com[rootid], world orientation
    vel = lin + np.cross(ang, d.xipos[1:] - root_com)
    inertia = np.stack([np.diag(i) for i in m.body_inertia[1:]])
    return quantities(m.body_mass[1:], d.xipos[1:], d.ximat[1:].reshape(-1, 3, 3), inertia, vel, ang, m.opt.gravity)


def rest_energy(scene: Scene, m: mujoco.MjModel) -> float:
    """Energy of the scene's rest pose (qpos0, at rest): the pendulum hanging straight down; 0 in zero gravity."""
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    return float(mujoco_quantities(m, d)["energy"])


def starts(scene: Scene, m: mujoco.MjModel, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    qpos, qvel = zip(*(scene.start(m, rng) for _ in range(SAMPLES)))
    return np.array(qpos), np.array(qvel)


def drifts(series: dict, scene: Scene, mass: float, e_rest: float) -> dict:
    """Per conserved quantity, max over time and starts of ``|Q(t) - Q(0)| / scale`` from ``series`` ``(T, B, ...)``."""
    scale = dict(linear_momentum=np.sqrt(2 * mass * series["kinetic"][0]), angular_momentum=np.linalg.norm(
        series["angular_momentum"][0], axis=-1), energy=series["energy"][0] - e_rest)
    out = {}
    for k in scene.conserved:
        dev = np.abs(series[k] - series[k][0])
        dev = np.linalg.norm(dev, axis=-1) if dev.ndim == 3 else dev
        out[k] = float(np.max(dev / scale[k])) if np.isfinite(dev).all() else math.inf
    out["energy_final"] = float(np.mean((series["energy"][-1] - series["energy"][0]) / scale["energy"]))
    return out


def load(scene: Scene, h: float, method: str) -> torchsim.System:
    return torchsim.load_mjcf(scene.mjcf(h), method=method, substeps=1, dtype=torch.float64)


def check_start(scene: Scene) -> float:
    """Largest difference at t = 0 between torchsim's and MuJoCo's quantities (relative to each one's scale), and
    between ours from MuJoCo's bodies and MuJoCo's own ``subtree_linvel``/``subtree_angmom``/``energy``."""
    m = mujoco.MjModel.from_xml_string(scene.mjcf(1e-3))
    m.opt.enableflags |= mujoco.mjtEnableBit.mjENBL_ENERGY
    d = mujoco.MjData(m)
    qpos, qvel = starts(scene, m)
    sys = load(scene, 1e-3, "spring")
    state = torchsim.init(sys, *(torch.tensor(x, dtype=torch.float64) for x in (qpos, qvel)))
    ours = torchsim_quantities(sys, *state[:4])
    worst = 0.0
    for b in range(SAMPLES):
        d.qpos[:], d.qvel[:] = qpos[b], qvel[b]
        mujoco.mj_forward(m, d)
        mujoco.mj_subtreeVel(m, d)
        theirs = mujoco_quantities(m, d)
        scale = dict(linear_momentum=np.sqrt(2 * m.body_mass.sum() * theirs["kinetic"]),
                     angular_momentum=np.linalg.norm(theirs["angular_momentum"]),
                     energy=theirs["kinetic"] + abs(theirs["energy"]))
        scale["kinetic"] = scale["energy"]
        assert (m.body_rootid[1:] == 1).all()  # one tree: body 1's subtree is every moving body
        own = dict(linear_momentum=d.subtree_linvel[1] * m.body_subtreemass[1], angular_momentum=d.subtree_angmom[1],
                   energy=d.energy.sum(), kinetic=d.energy[1])
        for k in (*QUANTITIES, "kinetic"):
            for other in (ours[k][b], own[k]):
                worst = max(worst, float(np.max(np.abs(other - theirs[k]))) / scale[k])
    return worst
