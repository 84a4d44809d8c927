"""MJCF snippets and helpers shared by the torchsim tests (no engine code here)."""

from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch

REPO = Path(__file__).resolve().parent.parent
ANT = REPO / "envs" / "assets" / "ant.xml"
HUMANOID = REPO / "envs" / "assets" / "humanoid.xml"
#: Every model the envs ship (MJCF, and the UR5e's URDF, which ``load_model`` translates).
SHIPPED = sorted(p for p in ANT.parent.iterdir() if p.suffix in (".xml", ".urdf"))
METHODS = ["xpbd", "spring"]
F64 = torch.float64

# A 0.5 m pendulum (capsule rod, sphere bob) on a hinge about y, 1 ms timestep.
PENDULUM = """
<mujoco><option timestep="0.001"/><worldbody>
  <body pos="0 0 1"><joint type="hinge" axis="0 1 0"/>
    <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.02"/><geom type="sphere" pos="0 0 -0.5" size="0.05"/>
  </body></worldbody></mujoco>"""

# A single free sphere that touches nothing (no floor, contype = conaffinity = 0), 1 ms timestep.
PROJECTILE = """
<mujoco model="projectile">
  <option timestep="0.001"/>
  <worldbody>
    <body name="ball" pos="0.1 -0.2 1.0">
      <freejoint/>
      <geom type="sphere" size="0.05" mass="1.5" contype="0" conaffinity="0"/>
    </body>
  </worldbody>
</mujoco>
"""

# A free body with principal inertias 1 : 2 : 3 [kg m^2], no gravity, nothing to touch. The inertial frame is
# offset and rotated from the body frame (ipos/iquat) so the test also covers how the loader turns MuJoCo's
# principal-axis inertia into the body-frame tensor. SPIN_IQUAT is the principal frame in the body frame.
SPIN_IQUAT = (0.9238795325112867, 0.0, 0.3826834323650898, 0.0)  # 45 deg about body y
SPIN = f"""
<mujoco model="spin">
  <option timestep="0.001" gravity="0 0 0"/>
  <worldbody>
    <body name="box" pos="0 0 1">
      <freejoint/>
      <inertial pos="0.05 -0.02 0.01" quat="{' '.join(map(str, SPIN_IQUAT))}" mass="2" diaginertia="1 2 3"/>
      <geom type="box" size="0.01 0.01 0.01" contype="0" conaffinity="0"/>
    </body>
  </worldbody>
</mujoco>
"""

# Three-body scene for contact-pair filtering: two free spheres over a plane (default contype/conaffinity = 1).
TWO_SPHERES = """
<mujoco>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.1" {floor}/>
    <body name="a" pos="0 0 0.5"><freejoint/><geom name="ga" type="sphere" size="0.1" {geom}/></body>
    <body name="b" pos="0 0 0.8"><freejoint/><geom name="gb" type="sphere" size="0.1" {geom}/></body>
  </worldbody>
  {extra}
</mujoco>
"""

# Parent with a child on a hinge and a grandchild on a hinge; all spheres overlap at the same point.
CHAIN = """
<mujoco>
  <option><flag filterparent="{filterparent}"/></option>
  <worldbody>
    <body name="parent" pos="0 0 1"><freejoint/>
      <geom name="g_parent" type="sphere" size="0.1"/>
      <body name="child" pos="0.05 0 0"><joint type="hinge" axis="0 1 0"/>
        <geom name="g_child" type="sphere" size="0.1"/>
        <body name="grandchild" pos="-0.05 0 0"><joint type="hinge" axis="0 1 0"/>
          <geom name="g_grandchild" type="sphere" size="0.1"/>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>
"""

# Two hinged links on a fixed base: a template for the unsupported-element tests.
TWO_HINGES = """
<mujoco>
  <worldbody>
    <body name="l1" pos="0 0 1"><joint name="h1" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" contype="0" conaffinity="0"/>
      <body name="l2" pos="0.3 0 0"><joint name="h2" type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" contype="0" conaffinity="0"/>
      </body>
    </body>
  </worldbody>
  {extra}
</mujoco>
"""


def quat_to_mat(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (..., 3, 3) of unit quaternions wxyz (independent of torchsim.spatial)."""
    w, x, y, z = q.unbind(-1)
    rows = [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]
    return torch.stack(rows, -1).reshape(q.shape[:-1] + (3, 3))


def quat_dist(a, b):
    """Max-abs difference of quaternions up to sign (q and -q are the same rotation)."""
    a, b = torch.as_tensor(a), torch.as_tensor(b)
    return torch.minimum((a - b).abs().amax(-1), (a + b).abs().amax(-1))


def random_q(m: mujoco.MjModel, batch: int, rng: np.random.Generator) -> np.ndarray:
    """qpos samples: free joints at a random position (|x| <= 1) and uniformly random orientation, hinges and
    slides uniform within their range (or +-pi where unlimited), ball joints uniformly random."""
    q = np.tile(m.qpos0, (batch, 1))
    for j in range(m.njnt):
        a = m.jnt_qposadr[j]
        kind = m.jnt_type[j]
        if kind == mujoco.mjtJoint.mjJNT_FREE:
            q[:, a:a + 3] = rng.uniform(-1, 1, (batch, 3))
            quat = rng.normal(size=(batch, 4))
            q[:, a + 3:a + 7] = quat / np.linalg.norm(quat, axis=1, keepdims=True)
        elif kind == mujoco.mjtJoint.mjJNT_BALL:
            quat = rng.normal(size=(batch, 4))
            q[:, a:a + 4] = quat / np.linalg.norm(quat, axis=1, keepdims=True)
        else:
            lo, hi = m.jnt_range[j] if m.jnt_limited[j] else (-np.pi, np.pi)
            q[:, a] = rng.uniform(lo, hi, batch)
    return q


def mid_range_q(m: mujoco.MjModel, lift: float = 0.0) -> np.ndarray:
    """qpos0 with every limited hinge/slide at the middle of its range, the root raised by ``lift`` [m]."""
    q = m.qpos0.copy()
    for j in range(m.njnt):
        if m.jnt_type[j] in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE) and m.jnt_limited[j]:
            q[m.jnt_qposadr[j]] = m.jnt_range[j].mean()
    q[2] += lift
    return q


def load_model(path: Path) -> tuple[str, mujoco.MjModel]:
    """A shipped model's MJCF text (a URDF as the env translates it) and its MuJoCo model."""
    from torchsim.io_urdf import urdf_to_mjcf  # engine code, imported where a test asks for it

    xml = urdf_to_mjcf(path) if path.suffix == ".urdf" else path.read_text()
    return xml, mujoco.MjModel.from_xml_string(xml)


def rest_pose(xml: str, method: str, seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """The model's final ``qpos`` in MuJoCo and ``q`` in torchsim (float64, eager, zero controls) after ``seconds``
    from ``qpos0`` at rest; asserts torchsim did not diverge."""
    import torchsim  # engine code, imported where a test asks for it

    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    for _ in range(round(seconds / m.opt.timestep)):
        mujoco.mj_step(m, d)
    sys = torchsim.load_mjcf(xml, method=method, dtype=F64)
    state = torchsim.init(sys, sys.q0[None].clone(), torch.zeros(1, sys.nv, dtype=F64))
    ctrl = torch.zeros(1, sys.nu, dtype=F64)
    for _ in range(round(seconds / sys.timestep)):
        state = torchsim.step(sys, state, ctrl)
    assert not state.diverged.any()
    return d.qpos.copy(), state.q[0].numpy()


def mujoco_rollout(xml: str, q0, qd0, steps: int, divide: int = 1) -> np.ndarray:
    """MuJoCo's ``qpos`` ``(steps, nq)`` after each of ``steps`` timesteps of ``xml`` from ``q0``, ``qd0`` (zero
    controls), integrated at ``timestep / divide``."""
    m = mujoco.MjModel.from_xml_string(xml)
    m.opt.timestep /= divide
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = q0, qd0
    out = []
    for _ in range(steps):
        mujoco.mj_step(m, d, nstep=divide)
        out.append(d.qpos.copy())
    return np.array(out)


def rollout_errors(sys, q0, qd0, reference: np.ndarray) -> tuple[float, float]:
    """torchsim's passive rollout of ``sys`` (batch 1, eager, zero controls) from ``q0``, ``qd0`` for the steps of
    ``reference (steps, nq)``: the largest ``|q - reference|`` [rad or m] and the largest joint anchor gap [m]."""
    import torchsim  # engine code, imported where a test asks for it

    state = torchsim.init(sys, torch.as_tensor(q0, dtype=sys.dtype)[None], torch.as_tensor(qd0, dtype=sys.dtype)[None])
    ctrl = torch.zeros(1, sys.nu, dtype=sys.dtype)
    err = gap = 0.0
    for expected in reference:
        state = torchsim.step(sys, state, ctrl)
        err = max(err, np.abs(state.q[0].numpy() - expected).max())
        gap = max(gap, torchsim.kinematics.anchor_gap(sys, state).max().item())
    return err, gap


def cached_third_party(pattern: str) -> str:
    """The first file matching ``pattern`` (a glob below ``~/.cache/torchsim/third_party``, where
    ``studies/check_robot_models.py`` unpacks the packages' wheels); the test is skipped where none is."""
    paths = sorted((Path.home() / ".cache" / "torchsim" / "third_party").glob(pattern))
    if not paths:
        pytest.skip(f"{pattern} is not cached (studies/check_robot_models.py unpacks it)")
    return str(paths[0])


def kernel_beside_reference(per_env, start, steps: int = 20):
    """``steps`` steps of the step kernel (one thread) and of the reference step on ``per_env`` (a System with
    per-env mocap poses) from ``start``, zero controls: the stepper and both final states. Then the envs' mocap
    poses swapped: the stepper takes them as new inputs of the same kernel."""
    import torchsim  # engine code, imported where a test asks for it

    stepper = torchsim.Stepper(per_env, "kernel", threads=1)
    ctrl = torch.zeros(start.q.shape[0], per_env.nu, dtype=per_env.dtype)
    expected = got = start
    for _ in range(steps):
        expected, got = torchsim.step(per_env, expected, ctrl), stepper(got, ctrl)
    moved = stepper.for_system(per_env.replace(mocap_pos=per_env.mocap_pos.flip(0)))
    moved(got, ctrl)
    assert moved.num_kernels == 1 and moved._kernel() is stepper._kernel()
    return stepper, expected, got


def axis_z(quat) -> float:
    """World z component of a body's local z axis, for its ``wxyz`` quaternion."""
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, quat)
    return mat[8]
