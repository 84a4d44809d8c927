"""The rest-height scenes that ``tests/test_rest_heights.py`` asserts and ``studies/rest_heights.py`` tabulates
(its docstring has the reading): the Ant with its ankles on their limits, the Humanoid lying on its back with every
geom colliding, each settled in MuJoCo and in torchsim under zero control."""

import mujoco
import numpy as np
import torch

import torchsim
from torchsim.envs.base import asset_path

F64 = torch.float64
ANKLE_LIMIT = np.deg2rad(30.0)  # the ankles' limit nearest zero (ranges [30, 70] and [-70, -30] deg)
CLEARANCE = 2e-3  # the feet start this far above the floor [m]


def ant_xml() -> str:
    return asset_path("ant.xml").read_text()


def humanoid_lying_xml() -> str:
    xml = asset_path("humanoid.xml").read_text()
    colliding = xml.replace('contype="0" conaffinity="0" condim="3"', 'contype="1" conaffinity="0" condim="3"')
    assert colliding != xml, "humanoid.xml's geom default changed: update humanoid_lying_xml"
    return colliding


def lowest_point(m: mujoco.MjModel, d: mujoco.MjData, geoms) -> float:
    """Lowest world z of the given sphere/capsule geoms in ``d``'s pose (after ``mj_forward``)."""
    low = np.inf
    for g in geoms:
        axis = d.geom_xmat[g].reshape(3, 3)[:, 2]
        half = m.geom_size[g, 1] if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_CAPSULE else 0.0
        low = min(low, d.geom_xpos[g, 2] - half * abs(axis[2]) - m.geom_size[g, 0])
    return low


def ant_rest_start(m: mujoco.MjModel) -> np.ndarray:
    """Home pose with every ankle on its limit nearest zero and the feet ``CLEARANCE`` above the floor."""
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, 0)
    for j in range(m.njnt):
        if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE and m.joint(j).name.startswith("ankle"):
            adr = m.jnt_qposadr[j]
            d.qpos[adr] = np.sign(d.qpos[adr]) * ANKLE_LIMIT
    mujoco.mj_forward(m, d)
    feet = [g for g in range(m.ngeom) if m.geom_contype[g]]
    d.qpos[2] += CLEARANCE - lowest_point(m, d, feet)
    return d.qpos.copy()


def ant_home(m: mujoco.MjModel) -> np.ndarray:
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, 0)
    return d.qpos.copy()


def humanoid_lying_start(m: mujoco.MjModel) -> np.ndarray:
    q = m.qpos0.copy()
    q[2] = 0.1
    q[3:7] = [np.cos(-np.pi / 4), 0.0, np.sin(-np.pi / 4), 0.0]
    return q


#: name: (MJCF text, start pose of the MuJoCo model, seconds to settle, physics rows (method, contact model,
#: substeps or None for load_mjcf's default), the first being the env's default).
SCENES = {
    "ant": (ant_xml, ant_rest_start, 3.0, [("spring", "soft", None), ("spring", "impulse", None),
                                           ("spring", "articulated", None), ("xpbd", "impulse", None)]),
    "humanoid lying": (humanoid_lying_xml, humanoid_lying_start, 6.0, [("spring", "impulse", None),
                                                                       ("spring", "soft", None),
                                                                       ("xpbd", "impulse", None)]),
}


def mujoco_rest(xml: str, q0: np.ndarray, seconds: float, split: int = 1) -> tuple[np.ndarray, float]:
    """MuJoCo's ``qpos`` and largest |qvel| after ``seconds`` from ``q0`` at rest, at the model's step / ``split``."""
    m = mujoco.MjModel.from_xml_string(xml)
    m.opt.timestep /= split
    d = mujoco.MjData(m)
    d.qpos[:] = q0
    for _ in range(round(seconds / m.opt.timestep)):
        mujoco.mj_step(m, d)
    return d.qpos.copy(), float(np.abs(d.qvel).max())


def torchsim_rest(xml: str, q0: np.ndarray, seconds: float, method: str, contact_model: str,
                  substeps: int | None = None, dtype=F64) -> tuple[float, float, int]:
    """torchsim's torso height [m], largest |qd| after ``seconds`` (zero control, eager, one env) and substeps."""
    sys = torchsim.load_mjcf(xml, method=method, contact_model=contact_model, substeps=substeps, dtype=dtype)
    state = torchsim.init(sys, torch.tensor(q0, dtype=dtype)[None], torch.zeros(1, sys.nv, dtype=dtype))
    ctrl = torch.zeros(1, sys.nu, dtype=dtype)
    for _ in range(round(seconds / sys.timestep)):
        state = torchsim.step(sys, state, ctrl)
    assert not bool(state.diverged.any()), "torchsim diverged"
    return float(state.q[0, 2]), float(state.qd.abs().max()), int(sys.substeps)
