"""Fluid forces (MuJoCo's inertia-box model, ``torchsim.fluid``) against MuJoCo: the generalized force at random
velocities, a free body sinking through a viscous fluid, and gymnasium's swimmer under a constant control."""

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from models import F64, METHODS
from torchsim.fluid import fluid_wrench
from torchsim.kinematics import forward, with_world
from torchsim import spatial

# A free body of three geoms (its principal axes neither the body's nor the geoms') with a jointless child, fused
# into it by torchsim but a fluid element of its own in MuJoCo, in a wind.
FREE = """
<mujoco><option gravity="0 0 0" density="1200" viscosity="0.3" wind="0.4 -0.7 0.2"/><worldbody>
  <body pos="0 0 1" euler="10 20 30"><freejoint/>
    <geom type="box" size=".3 .1 .05" pos=".1 .05 0" euler="5 0 7"/><geom type="sphere" size=".1" pos="-.2 0 .1"/>
    <body pos=".3 0 0" euler="0 40 0"><geom type="capsule" size=".05" fromto="0 0 0 .4 0 .1"/></body>
  </body></worldbody></mujoco>"""

# A chain of capsules on a slide-slide-hinge root (the swimmer's joints) with a ball joint and 2-hinge joint below.
CHAIN = """
<mujoco><option gravity="0 0 0" density="3000" viscosity="0.1" wind="0.3 0 -0.2"/><worldbody>
  <body><joint type="slide" axis="1 0 0"/><joint type="slide" axis="0 1 0"/><joint type="hinge" axis="0 0 1"/>
    <geom type="capsule" size=".1" fromto="0 0 0 .8 0 0"/>
    <body pos="-.05 0 0"><joint type="hinge" axis="0 0 1"/><geom type="capsule" size=".08" fromto="0 0 0 -.7 .1 0"/>
      <body pos="-.75 .1 0"><joint type="ball"/><geom type="capsule" size=".06" fromto="0 0 0 -.5 0 .2"/>
        <body pos="-.5 0 .2"><joint type="hinge" axis="0 1 0"/><joint type="hinge" axis="1 0 0"/>
          <geom type="box" size=".2 .05 .02" pos="-.2 0 0"/></body></body></body>
  </body></worldbody></mujoco>"""


def _generalized_fluid_force(xml: str, rng: np.random.Generator, batch: int = 4):
    """MuJoCo's ``qfrc_passive`` and torchsim's fluid wrenches mapped through MuJoCo's Jacobians (``mj_applyFT`` at
    each fused body's COM), ``(batch, nv)`` each, at random poses and velocities."""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    sys = torchsim.load_mjcf(xml, dtype=F64)
    assert sys.fluid
    qpos, qvel, ref = [], [], []
    for _ in range(batch):
        d.qpos[:] = m.qpos0 + 0.5 * rng.normal(size=m.nq)
        mujoco.mj_normalizeQuat(m, d.qpos)
        d.qvel[:] = 2.0 * rng.normal(size=m.nv)
        mujoco.mj_forward(m, d)
        qpos.append(d.qpos.copy())
        qvel.append(d.qvel.copy())
        ref.append(d.qfrc_passive.copy())
    bodies = with_world(*forward(sys, torch.as_tensor(np.array(qpos)), torch.as_tensor(np.array(qvel))))
    force, torque = fluid_wrench(sys, bodies, spatial.quat_to_mat(bodies.x_quat))
    ours = np.zeros((batch, m.nv))
    roots = [b for b in range(1, m.nbody) if m.body_weldid[b] == b]
    for k in range(batch):
        d.qpos[:] = qpos[k]
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        for b in roots:
            i = int(sys.mjbody_body[b])
            mujoco.mj_applyFT(m, d, force[:, i, k].numpy(), torque[:, i, k].numpy(), bodies.x_pos[:, i, k].numpy(),
                              b, ours[k])
    return np.array(ref), ours


@pytest.mark.parametrize("xml", [FREE, CHAIN], ids=["free", "chain"])
def test_generalized_force_matches_mujoco(xml):
    ref, ours = _generalized_fluid_force(xml, np.random.default_rng(0))
    err = np.abs(ours - ref).max() / np.abs(ref).max()
    print(f"fluid qfrc vs MuJoCo: max |ref| {np.abs(ref).max():.3g}, relative error {err:.2e}")
    assert err < 1e-9


def test_no_fluid_is_static_structure():
    """No density or viscosity: no fluid elements and ``sys.fluid`` False (the step skips the fluid)."""
    sys = torchsim.load_mjcf(FREE.replace('density="1200" viscosity="0.3"', ""), dtype=F64)
    assert not sys.fluid and sys.fluid_body.numel() == 0


def test_ellipsoid_fluid_model_refused():
    xml = FREE.replace('<geom type="sphere"', '<geom type="sphere" name="head" fluidshape="ellipsoid"')
    with pytest.raises(torchsim.UnsupportedMJCFError, match="head.*fluidshape"):
        torchsim.load_mjcf(xml)


# A free box thrown sideways and spinning, sinking through a viscous, dense fluid under gravity.
SINK = """
<mujoco><option timestep="{dt}" density="800" viscosity="2"/><worldbody>
  <body pos="0 0 1" euler="0 30 0"><freejoint/><geom type="box" size=".2 .1 .03" density="1500"/></body>
</worldbody></mujoco>"""


def _mujoco_sink(xml: str, dt: float, duration: float, qvel0: np.ndarray) -> np.ndarray:
    """``(qpos, qvel)`` ``(steps, 13)`` after each step of ``dt`` from the model's ``qpos0`` and ``qvel0``."""
    m = mujoco.MjModel.from_xml_string(xml.format(dt=dt))
    d = mujoco.MjData(m)
    d.qvel[:] = qvel0
    out = []
    for _ in range(round(duration / dt)):
        mujoco.mj_step(m, d)
        out.append(np.concatenate((d.qpos, d.qvel)))
    return np.array(out)


@pytest.mark.parametrize("method", METHODS)
def test_sinking_body_follows_mujoco(method):
    """Over 0.5 s, the body's position and velocities stay within 3x MuJoCo's own step error (MuJoCo at dt = 10 ms
    against dt/4, per component) of MuJoCo at dt/4, the substep torchsim takes: both integrate the drag explicitly
    and differ in the gyroscopic term (torchsim's is implicit), which puts torchsim's error at up to 1.4x MuJoCo's
    (the spin about z; 0.06 rad/s at most), while the fluid changes the motion by 8 (m/s, rad/s): 50x is asked."""
    dt, duration = 0.01, 0.5
    qvel0 = np.array([2.0, 0.5, 1.0, 3.0, -8.0, 4.0])
    coarse, fine = _mujoco_sink(SINK, dt, duration, qvel0), _mujoco_sink(SINK, dt / 4, duration, qvel0)[3::4]
    dry = _mujoco_sink(SINK.replace('density="800" viscosity="2"', ""), dt, duration, qvel0)
    sys = torchsim.load_mjcf(SINK.format(dt=dt), method=method, substeps=4, dtype=F64)
    state = torchsim.init(sys, sys.q0[None], torch.as_tensor(qvel0[None]))
    ours = []
    for _ in range(len(coarse)):
        state = torchsim.step(sys, state, torch.zeros(1, 0, dtype=F64))
        ours.append(np.concatenate((state.q[0].numpy(), state.qd[0].numpy())))
    cols = [0, 1, 2, 7, 8, 9, 10, 11, 12]  # position, linear and angular velocity
    err, mj_err, effect = (np.abs(x[:, cols] - fine[:, cols]).max(0) for x in (np.array(ours), coarse, dry))
    print(f"{method}: max error vs MuJoCo dt/4 {np.array2string(err, precision=4)}, MuJoCo dt vs dt/4 "
          f"{np.array2string(mj_err, precision=4)}, fluid effect {effect.max():.2f}")
    assert np.all(err <= 3 * mj_err) and effect.max() > 50 * err.max()


# gymnasium's swimmer.xml (v5 assets) without its visuals: same bodies, joints, actuators and options.
SWIMMER = """
<mujoco model="swimmer">
  <compiler angle="degree" coordinate="local" inertiafromgeom="true"/>
  <option density="4000" integrator="RK4" timestep="0.01" viscosity="0.1"/>
  <default><geom conaffinity="0" condim="1" contype="0"/><joint armature='0.1'/></default>
  <worldbody>
    <geom condim="3" name="floor" pos="0 0 -0.1" size="40 40 0.1" type="plane"/>
    <body name="torso" pos="0 0 0">
      <geom density="1000" fromto="1.5 0 0 0.5 0 0" size="0.1" type="capsule"/>
      <joint axis="1 0 0" name="slider1" pos="0 0 0" type="slide"/>
      <joint axis="0 1 0" name="slider2" pos="0 0 0" type="slide"/>
      <joint axis="0 0 1" name="free_body_rot" pos="0 0 0" type="hinge"/>
      <body name="mid" pos="0.5 0 0">
        <geom density="1000" fromto="0 0 0 -1 0 0" size="0.1" type="capsule"/>
        <joint axis="0 0 1" limited="true" name="motor1_rot" pos="0 0 0" range="-100 100" type="hinge"/>
        <body name="back" pos="-1 0 0">
          <geom density="1000" fromto="0 0 0 -1 0 0" size="0.1" type="capsule"/>
          <joint axis="0 0 1" limited="true" name="motor2_rot" pos="0 0 0" range="-100 100" type="hinge"/>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor ctrllimited="true" ctrlrange="-1 1" gear="150.0" joint="motor1_rot"/>
    <motor ctrllimited="true" ctrlrange="-1 1" gear="150.0" joint="motor2_rot"/>
  </actuator>
</mujoco>"""


def _mujoco_swimmer(xml: str, dt: float, duration: float, ctrl: list) -> np.ndarray:
    """qpos ``(steps, 5)`` of MuJoCo's swimmer (its RK4) every 0.01 s, stepped at ``dt``."""
    m = mujoco.MjModel.from_xml_string(xml.replace('timestep="0.01"', f'timestep="{dt}"'))
    d = mujoco.MjData(m)
    d.ctrl[:] = ctrl
    out = []
    for _ in range(round(duration / dt)):
        mujoco.mj_step(m, d)
        out.append(d.qpos.copy())
    return np.array(out)[round(0.01 / dt) - 1::round(0.01 / dt)]


@pytest.mark.parametrize("method,substeps", [("spring", 10), ("xpbd", 4)])
def test_swimmer_moves_like_mujoco(method, substeps):
    """Gymnasium's swimmer under a constant control for 0.4 s: its position, heading and joint angles stay within
    0.05 [m | rad] of MuJoCo's (RK4 at 2.5 ms, which agrees with its 10 ms to 5e-8) at every step: a little above
    each method's own gap to MuJoCo on this swimmer without a fluid (spring at 10 substeps: 0.037, xpbd at 4:
    0.012; with the fluid 0.021 and 0.006), where the fluid changes the motion by up to 0.28 rad, which torchsim
    without it would miss by."""
    duration, ctrl = 0.4, [0.2, -0.1]
    ref = _mujoco_swimmer(SWIMMER, 0.0025, duration, ctrl)
    dry = _mujoco_swimmer(SWIMMER.replace('density="4000" ', "").replace(' viscosity="0.1"', ""), 0.01, duration, ctrl)
    sys = torchsim.load_mjcf(SWIMMER, method=method, substeps=substeps, dtype=F64)
    state = torchsim.init(sys, torch.zeros(1, sys.nq, dtype=F64), torch.zeros(1, sys.nv, dtype=F64))
    ours = []
    for _ in range(len(ref)):
        state = torchsim.step(sys, state, torch.tensor([ctrl], dtype=F64))
        ours.append(state.q[0].numpy().copy())
    err, effect = np.abs(np.array(ours) - ref).max(0), np.abs(dry - ref).max(0)
    print(f"{method}: max error vs MuJoCo {np.array2string(err, precision=4)}, "
          f"fluid effect {np.array2string(effect, precision=3)}")
    assert err.max() < 0.05 and effect.max() > 0.25
