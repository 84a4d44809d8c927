"""Site transmission (``torchsim.site_actuators``): actuator length, velocity, moment arms and generalized forces
against MuJoCo's, with and without a refsite, and a driven arm's path against MuJoCo's."""

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from torchsim import actuators, lanes, site_actuators
from torchsim.io_mjcf import UnsupportedMJCFError, load_mjcf
from torchsim.kinematics import dof_values, forward, joint_frames, with_world

#: A three-link arm (hinges about z and y, then a slide, with a welded hand between) and a free-floating block; sites
#: at offsets and tilts on the hand, the slider, the upper arm, the world and the block. Actuators: site motors
#: without a refsite, Cartesian ones with a refsite on another moving body and on the world (with affine bias on
#: length and velocity), a thruster on the free block, and one joint motor.
SITES = """
<mujoco><option timestep="{dt}"/>
  <worldbody>
    <site name="base" pos="0.1 0.2 0.3" quat="0.9 0.1 0.3 0.2"/>
    <body name="upper" pos="0 0 1"><joint name="yaw" type="hinge" axis="0 0 1" damping="0.1"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="1"/>
      <site name="ref" pos="0.1 0.05 0" quat="0.8 0.3 -0.2 0.1"/>
      <body name="lower" pos="0.3 0 0"><joint name="pitch" type="hinge" axis="0 1 0" damping="0.1"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="0.5"/>
        <body name="hand" pos="0.3 0 0" quat="0.9 0 0.3 0.1">
          <geom type="sphere" size="0.05" pos="0.02 0 0" mass="0.2"/>
          <site name="ee" pos="0.05 0.01 0.02" quat="0.7 0.2 0.5 -0.1"/>
        </body>
        <body name="slider" pos="0.3 0 0"><joint name="slide" type="slide" axis="1 0 0" damping="1"/>
          <geom type="sphere" size="0.04" mass="0.3"/><site name="tip" pos="0.02 0 0.01"/>
        </body>
      </body>
    </body>
    <body name="block" pos="1 1 1"><freejoint/><geom type="box" size="0.1 0.05 0.03" pos="0.01 0 0" mass="0.4"/>
      <site name="thruster" pos="0.05 0.02 -0.03" quat="0.95 0.1 0.2 0"/>
    </body>
  </worldbody>
  <actuator>
    <motor site="ee" gear="1 0.5 -0.2 0.1 -0.4 0.3"/>
    <general site="ee" refsite="ref" gear="0.2 1 0.3 0.3 0.1 -0.5" biastype="affine" biasprm="0.1 -2 -0.5"/>
    <general site="tip" refsite="base" gear="0.5 -0.3 0.7 0.2 0.6 0.1" biastype="affine" biasprm="0 -1 -0.3"/>
    <motor site="thruster" gear="0.3 0 4 0 0.02 0"/>
    <motor joint="yaw" gear="2"/>
  </actuator>
</mujoco>"""
DT = 0.002


def _random_states(m: mujoco.MjModel, count: int, rng: np.random.Generator):
    """``count`` random ``(qpos, qvel)`` (the free block's quaternion random too)."""
    for _ in range(count):
        qpos = rng.uniform(-1.5, 1.5, m.nq)
        qpos[m.jnt_qposadr[-1] + 3:] /= np.linalg.norm(qpos[m.jnt_qposadr[-1] + 3:])
        yield qpos, rng.normal(size=m.nv)


def _bodies(sys, qpos, qvel):
    """Lanes bodies (with the world) at ``qpos``, ``qvel`` ``(nq | nv,)`` or a batch of them."""
    return with_world(*forward(sys, torch.as_tensor(np.atleast_2d(qpos)), torch.as_tensor(np.atleast_2d(qvel))))


def _unit_motions(sys, qpos):
    """The bodies at ``qpos`` moving at a unit ``qvel`` in each dof (a batch of ``nv``): their velocities are the
    columns of the bodies' Jacobians, by which a wrench on the bodies is a generalized force, and an actuator's
    velocity is its moment arm."""
    return _bodies(sys, np.tile(qpos, (sys.nv, 1)), np.eye(sys.nv))


def test_length_velocity_and_moment_are_mujocos():
    """At random states, every site actuator's ``actuator_length``, ``actuator_velocity`` and moment arms (the
    velocity of a unit qvel in each dof) equal MuJoCo's to float64 rounding; the moment arms of a refsite on a moving
    body included (MuJoCo takes both bodies' Jacobians at the site)."""
    xml = SITES.format(dt=DT)
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    sys = load_mjcf(xml, dtype=torch.float64)
    rows = sys.site_act_actuator.numpy()
    for qpos, qvel in _random_states(m, 4, np.random.default_rng(0)):
        d.qpos[:], d.qvel[:] = qpos, qvel
        mujoco.mj_forward(m, d)
        site = site_actuators.coordinates(sys, _bodies(sys, qpos, qvel))
        np.testing.assert_allclose(site.length[:, 0].numpy(), d.actuator_length[rows], rtol=0, atol=1e-12)
        np.testing.assert_allclose(site.velocity[:, 0].numpy(), d.actuator_velocity[rows], rtol=0, atol=1e-10)
        moment = np.zeros((m.nu, m.nv))
        mujoco.mju_sparse2dense(moment, d.actuator_moment, d.moment_rownnz, d.moment_rowadr, d.moment_colind)
        arms = site_actuators.coordinates(sys, _unit_motions(sys, qpos)).velocity
        np.testing.assert_allclose(arms.numpy(), moment[rows], rtol=0, atol=1e-10)


def test_generalized_forces_are_mujocos():
    """The wrenches ``actuators.body_wrench`` puts on the bodies, read as generalized forces through the bodies'
    Jacobians (their power at a unit qvel in each dof), equal MuJoCo's ``qfrc_actuator`` (site actuators with their
    affine biases, and the joint motor) to float64 rounding."""
    xml = SITES.format(dt=DT)
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    sys = load_mjcf(xml, dtype=torch.float64)
    rng = np.random.default_rng(1)
    for qpos, qvel in _random_states(m, 4, rng):
        d.qpos[:], d.qvel[:], d.ctrl[:] = qpos, qvel, rng.normal(size=m.nu)
        mujoco.mj_forward(m, d)
        bodies = _bodies(sys, qpos, qvel)
        frames = joint_frames(sys, bodies)
        q_dof = lanes.to_lanes(torch.as_tensor(qpos)[None]).index_select(0, sys.dof_qpos)
        qd_dof = lanes.to_lanes(torch.as_tensor(qvel)[None]).index_select(0, sys.dof_qvel)
        force, torque = actuators.body_wrench(sys, bodies, dof_values(sys, frames.axes), q_dof, qd_dof,
                                              lanes.to_lanes(torch.as_tensor(d.ctrl)[None]))
        unit = _unit_motions(sys, qpos)
        qfrc = (force * unit.xd_vel).sum((0, 1)) + (torque * unit.xd_ang).sum((0, 1))
        np.testing.assert_allclose(qfrc.numpy(), d.qfrc_actuator, rtol=0, atol=1e-10)


#: A two-link arm swinging in the x-z plane and a free block, driven only through sites: a site motor on the hand,
#: Cartesian actuators from the hand to a refsite on the upper arm and to one on the world (springs and dampers on
#: their lengths), and a thruster under the block.
ARM = """
<mujoco><option timestep="{dt}"/>
  <worldbody>
    <site name="anchor" pos="0.4 0 0.8" quat="0.9 0 0.3 0"/>
    <body name="upper" pos="0 0 1"><joint name="shoulder" type="hinge" axis="0 1 0" damping="0.05"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="1"/>
      <site name="elbow_ref" pos="0.25 0 0.02" quat="0.95 0 0.3 0"/>
      <body name="lower" pos="0.3 0 0"><joint name="elbow" type="hinge" axis="0 1 0" damping="0.05"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="0.5"/>
        <site name="hand" pos="0.3 0 0.01" quat="0.8 0.1 0.5 0.2"/></body>
    </body>
    <body name="block" pos="1 1 1"><freejoint/><geom type="box" size="0.1 0.05 0.03" mass="0.4"/>
      <site name="thruster" pos="0 0 -0.03"/></body>
  </worldbody>
  <actuator>
    <motor site="hand" gear="0.5 0.2 1 0 0.1 0"/>
    <general site="hand" refsite="elbow_ref" gear="1 0 0.5 0 0.2 0" biastype="affine" biasprm="0 -3 -0.3"/>
    <general site="hand" refsite="anchor" gear="0 0 1 0 0 0" biastype="affine" biasprm="0 -5 -0.5"/>
    <motor site="thruster" gear="0.2 0 3 0 0 0"/>
  </actuator>
</mujoco>"""


def _control(t: float) -> np.ndarray:
    return np.array([np.sin(5 * t), 2 * np.cos(4 * t), np.sin(7 * t), 1.5 + np.sin(3 * t)])


def _mujoco_path(steps: int, split: int = 1, control=_control) -> np.ndarray:
    m = mujoco.MjModel.from_xml_string(ARM.format(dt=DT / split))
    d = mujoco.MjData(m)
    path = []
    for k in range(steps):
        d.ctrl[:] = control(k * DT)
        for _ in range(split):
            mujoco.mj_step(m, d)
        path.append(d.qpos.copy())
    return np.array(path)


def test_path_against_mujoco():
    """The arm and the block driven through their sites for 0.4 s follow MuJoCo's path as closely as MuJoCo's path
    with a 4x finer step does: within 1.5x MuJoCo's dt vs dt/4 difference (measured: 1.0x, 4.5e-3 rad at most).
    MuJoCo's own path without the controls is 50x that far off: the bound tests the site actuators."""
    steps = 200
    sys = load_mjcf(ARM.format(dt=DT), dtype=torch.float64)
    state = torchsim.init(sys, sys.q0[None], torch.zeros(1, sys.nv, dtype=torch.float64))
    ours = []
    for k in range(steps):
        state = torchsim.step(sys, state, torch.as_tensor(_control(k * DT))[None])
        ours.append(state.q[0].numpy())
    theirs, finer = _mujoco_path(steps), _mujoco_path(steps, split=4)
    idle = _mujoco_path(steps, control=lambda t: np.zeros(4))
    own_error, error = np.abs(theirs - finer).max(), np.abs(np.array(ours) - theirs).max()
    assert error < 1.5 * own_error, (error, own_error)
    assert np.abs(idle - theirs).max() > 50 * own_error


def test_kernel_steps_site_actuators():
    """The step kernel runs a model with site actuators: 10 float64 steps equal the reference step's to 1e-10."""
    sys = load_mjcf(SITES.format(dt=DT), dtype=torch.float64)
    stepper = torchsim.Stepper(sys)
    stepper.build()
    assert stepper.strategy == "kernel"
    ours = reference = torchsim.init(sys, sys.q0.expand(2, -1), torch.zeros(2, sys.nv, dtype=torch.float64))
    for k in range(10):
        ctrl = torch.linspace(-1, 1, 2 * sys.nu, dtype=torch.float64).reshape(2, -1) * (k + 1) / 10
        ours, reference = stepper(ours, ctrl), torchsim.step(sys, reference, ctrl)
    for a, b in zip(ours, reference):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-10)


def test_actuator_sensors_are_skipped_with_a_reason():
    """Sensors do not read site actuators' coordinates yet: an actuator sensor of a model with site transmission is
    skipped, with the reason named, not read wrong."""
    xml = SITES.format(dt=DT).replace("</actuator>", "</actuator><sensor><actuatorpos actuator=\"yaw\"/></sensor>")
    with pytest.warns(UserWarning, match="actuatorpos"):
        sys = load_mjcf(xml.replace('<motor joint="yaw"', '<motor name="yaw" joint="yaw"'))
    assert sys.sensor_skipped == ("actuators with site transmission are not read by sensors yet",)


def test_body_transmission_is_refused_by_name():
    xml = SITES.format(dt=DT).replace('<motor joint="yaw" gear="2"/>', '<adhesion body="block" ctrlrange="0 1"/>')
    with pytest.raises(UnsupportedMJCFError, match=r"body transmission \(adhesion\)"):
        load_mjcf(xml)
