"""Sensors (``torchsim.sensors``) against MuJoCo 4.0's ``sensordata``: every computed type on one small model
(a free torso with a hinged arm whose hand is fused into it, a slide-and-hinge body, a ball joint, a fixed tendon,
joint, servo, damper and tendon actuators, sites, geoms and a camera as sensor objects and references, a static
body fused into the world), read at the same state MuJoCo's ``mj_forward`` reads; the types torchsim does not
compute warn once and raise when read."""

import re
import warnings

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from models import F64, PENDULUM, random_q

MODEL = """
<mujoco>
  <compiler angle="radian"/>
  <option timestep="0.002" magnetic="0.1 -0.4 0.3"/>
  <worldbody>
    <body name="static" pos="1 0 0.5" quat="0.9 0.1 0.3 0">
      <geom type="box" size=".1 .1 .1" contype="0" conaffinity="0"/>
      <site name="static_site" pos="0.1 0 0"/>
    </body>
    <body name="torso" pos="0 0 1">
      <freejoint name="root"/>
      <geom name="torso_geom" type="box" size=".2 .1 .05" pos=".02 0 .01" quat="1 .1 0 .2" contype="0" conaffinity="0"/>
      <site name="imu" pos=".1 .05 -.02" quat="0.8 0.2 -0.3 0.1"/>
      <camera name="cam" pos="-.3 0 .1" xyaxes="0 -1 0 .5 0 .8"/>
      <body name="arm" pos=".2 0 0">
        <joint name="shoulder" type="hinge" axis="0 1 0" ref="0.3" range="-1 1" margin="0.4"/>
        <geom type="capsule" fromto="0 0 0 .3 0 0" size=".03" contype="0" conaffinity="0"/>
        <body name="hand" pos=".3 0 0" quat="0.9 0 0.2 0.1">
          <geom name="hand_geom" type="box" size=".05 .04 .03" pos=".02 .01 0" quat="1 0 .3 0" contype="0"
                conaffinity="0"/>
          <site name="fingertip" pos=".05 0 .01" quat="0.7 0 0.7 0.1"/>
        </body>
      </body>
      <body name="slider" pos="-.2 0 0">
        <joint name="slide" type="slide" axis="1 0 0" range="-.2 .2" margin=".05" stiffness="40" armature=".1"/>
        <joint name="twist" type="hinge" axis="1 0 0" stiffness="3" springref=".4" armature=".02"/>
        <geom type="box" size=".05 .05 .05" contype="0" conaffinity="0"/>
      </body>
      <body name="head" pos="0 0 .1">
        <joint name="neck" type="ball"/>
        <geom type="sphere" size=".06" pos="0 0 .05" contype="0" conaffinity="0"/>
      </body>
    </body>
  </worldbody>
  <tendon>
    <fixed name="tendon" limited="true" range="-.5 .5" margin=".2" stiffness="7" springlength="-.1 .1">
      <joint joint="shoulder" coef="1"/><joint joint="slide" coef="-2"/>
    </fixed>
  </tendon>
  <actuator>
    <motor name="shoulder_motor" joint="shoulder" gear="2" ctrlrange="-1 1" ctrllimited="true"/>
    <position name="slide_servo" joint="slide" kp="50" kv="3" forcerange="-5 5" forcelimited="true"/>
    <velocity name="twist_damper" joint="twist" kv="2"/>
    <motor name="tendon_motor" tendon="tendon" gear="1.5"/>
  </actuator>
  <sensor>
    <jointpos name="shoulder_pos" joint="shoulder"/>
    <jointpos name="slide_pos" joint="slide"/>
    <jointvel name="twist_vel" joint="twist"/>
    <jointvel name="clipped_vel" joint="shoulder" cutoff="0.5"/>
    <ballquat name="neck_quat" joint="neck"/>
    <ballangvel name="neck_vel" joint="neck"/>
    <tendonpos name="tendon_len" tendon="tendon"/>
    <tendonvel name="tendon_vel" tendon="tendon"/>
    <actuatorpos name="servo_len" actuator="slide_servo"/>
    <actuatorpos name="tendon_motor_len" actuator="tendon_motor"/>
    <actuatorvel name="motor_vel" actuator="shoulder_motor"/>
    <actuatorvel name="tendon_motor_vel" actuator="tendon_motor"/>
    <actuatorfrc name="motor_frc" actuator="shoulder_motor"/>
    <actuatorfrc name="servo_frc" actuator="slide_servo"/>
    <actuatorfrc name="damper_frc" actuator="twist_damper"/>
    <actuatorfrc name="tendon_motor_frc" actuator="tendon_motor"/>
    <jointactuatorfrc name="shoulder_frc" joint="shoulder"/>
    <jointactuatorfrc name="slide_frc" joint="slide"/>
    <tendonactuatorfrc name="tendon_frc" tendon="tendon"/>
    <jointlimitpos name="shoulder_limit" joint="shoulder"/>
    <jointlimitvel name="shoulder_limit_vel" joint="shoulder"/>
    <jointlimitpos name="slide_limit" joint="slide"/>
    <jointlimitvel name="slide_limit_vel" joint="slide"/>
    <tendonlimitpos name="tendon_limit" tendon="tendon"/>
    <tendonlimitvel name="tendon_limit_vel" tendon="tendon"/>
    <framepos name="tip_pos" objtype="site" objname="fingertip"/>
    <framepos name="tip_from_imu" objtype="site" objname="fingertip" reftype="site" refname="imu"/>
    <framepos name="torso_com" objtype="body" objname="torso"/>
    <framepos name="hand_origin" objtype="xbody" objname="hand"/>
    <framepos name="hand_geom_from_cam" objtype="geom" objname="hand_geom" reftype="camera" refname="cam"/>
    <framepos name="cam_pos" objtype="camera" objname="cam"/>
    <framepos name="static_from_torso" objtype="site" objname="static_site" reftype="xbody" refname="torso"/>
    <framequat name="arm_quat" objtype="xbody" objname="arm"/>
    <framequat name="tip_quat_torso" objtype="site" objname="fingertip" reftype="xbody" refname="torso"/>
    <framequat name="hand_inertia_quat" objtype="body" objname="hand" reftype="geom" refname="torso_geom"/>
    <framexaxis name="imu_x" objtype="site" objname="imu"/>
    <frameyaxis name="hand_geom_y" objtype="geom" objname="hand_geom" reftype="site" refname="imu"/>
    <framezaxis name="cam_z" objtype="camera" objname="cam"/>
    <framelinvel name="tip_vel" objtype="site" objname="fingertip"/>
    <framelinvel name="tip_vel_imu" objtype="site" objname="fingertip" reftype="site" refname="imu"/>
    <framelinvel name="hand_vel_arm" objtype="xbody" objname="hand" reftype="body" refname="slider"/>
    <frameangvel name="tip_angvel" objtype="site" objname="fingertip"/>
    <frameangvel name="tip_angvel_slider" objtype="site" objname="fingertip" reftype="xbody" refname="slider"/>
    <subtreecom name="torso_subtree" body="torso"/>
    <subtreecom name="hand_subtree" body="hand"/>
    <subtreecom name="world_subtree" body="world"/>
    <subtreelinvel name="torso_subtree_vel" body="torso"/>
    <subtreelinvel name="arm_subtree_vel" body="arm"/>
    <subtreeangmom name="torso_angmom" body="torso"/>
    <subtreeangmom name="arm_angmom" body="arm"/>
    <subtreeangmom name="hand_angmom" body="hand"/>
    <subtreeangmom name="world_angmom" body="world"/>
    <gyro name="imu_gyro" site="imu"/>
    <gyro name="tip_gyro" site="fingertip"/>
    <velocimeter name="tip_velocimeter" site="fingertip"/>
    <velocimeter name="imu_velocimeter" site="imu" cutoff="0.3"/>
    <magnetometer name="imu_mag" site="imu"/>
    <accelerometer name="imu_acc" site="imu"/>
    <touch name="tip_touch" site="fingertip"/>
    <e_potential name="potential"/>
    <e_kinetic name="kinetic"/>
    <clock name="time"/>
    <jointpos name="late" joint="twist" nsample="3" delay="0.004"/>
  </sensor>
</mujoco>
"""
#: Every type torchsim computes; the model has at least one sensor of each.
COMPUTED = ("jointpos", "jointvel", "ballquat", "ballangvel", "tendonpos", "tendonvel", "actuatorpos", "actuatorvel",
            "actuatorfrc", "jointactuatorfrc", "tendonactuatorfrc", "framepos", "framequat", "framexaxis",
            "frameyaxis", "framezaxis", "framelinvel", "frameangvel", "subtreecom", "subtreelinvel", "subtreeangmom",
            "gyro", "velocimeter", "magnetometer", "jointlimitpos", "jointlimitvel", "tendonlimitpos",
            "tendonlimitvel", "e_potential", "e_kinetic")
NOT_COMPUTED = {"time": "clock", "late": "jointpos.*delay"}
ENVS = 4
#: The shoulder and slide coordinates of the 4 envs: within the margin of the shoulder's lower and upper limits
#: (range -1..1 rad, margin 0.4) and of the slide's upper and lower limits (range -0.2..0.2 m, margin 0.05).
SHOULDER_AND_SLIDE = np.array([[-0.9, 0.0], [0.85, -0.05], [0.1, 0.19], [0.2, -0.18]])


def load() -> torchsim.System:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the not-computed sensors' warning: test_not_computed_types_warn_and_raise
        return torchsim.load_mjcf(MODEL, dtype=F64)


def mujoco_sensordata(m: mujoco.MjModel, q, qd, ctrl) -> np.ndarray:
    """MuJoCo's ``sensordata`` ``(B, nsensordata)`` after ``mj_forward`` at each env's state and controls."""
    d = mujoco.MjData(m)
    out = []
    for qpos, qvel, u in zip(q, qd, ctrl):
        d.qpos[:], d.qvel[:], d.ctrl[:] = qpos, qvel, u
        mujoco.mj_forward(m, d)
        out.append(d.sensordata.copy())
    return np.array(out)


def slots(sys: torchsim.System, kind: str) -> list:
    """The sensordata addresses of every computed sensor of ``kind``."""
    return [a + k for t, a, d, skipped in zip(sys.sensor_kinds, sys.sensor_adr, sys.sensor_dims, sys.sensor_skipped)
            if t == kind and not skipped for k in range(d)]


@pytest.fixture(scope="module")
def random_states():
    """Random states and controls (beyond ctrlrange, so clamping acts) of the model, torchsim's and MuJoCo's
    sensordata at them."""
    m, sys = mujoco.MjModel.from_xml_string(MODEL), load()
    rng = np.random.default_rng(0)
    q, qd, ctrl = random_q(m, ENVS, rng), rng.normal(0, 1.5, (ENVS, m.nv)), rng.uniform(-2, 2, (ENVS, m.nu))
    q[:, 7:9] = SHOULDER_AND_SLIDE
    state = torchsim.init(sys, torch.as_tensor(q), torch.as_tensor(qd))
    ours = torchsim.sensordata(sys, state, torch.as_tensor(ctrl)).numpy()
    return sys, state, torch.as_tensor(ctrl), ours, mujoco_sensordata(m, q, qd, ctrl)


@pytest.mark.parametrize("kind", COMPUTED)
def test_sensor_type_matches_mujoco(random_states, kind):
    """Each computed type equals MuJoCo's at the same state: both evaluate the same closed forms in float64, from
    body poses torchsim's ``init`` places to ~1e-13 m (the errors seen are 1e-14..3e-11), so 1e-9 leaves room for
    rounding and none for a wrong frame, sign or offset (those are >= 1e-3 here)."""
    sys, _, _, ours, theirs = random_states
    index = slots(sys, kind)
    assert index, f"the test model has no {kind} sensor"
    np.testing.assert_allclose(ours[:, index], theirs[:, index], rtol=0, atol=1e-9)


def test_cutoff_clamps_real_values(random_states):
    """``cutoff`` clamps as MuJoCo's does: the clipped joint velocity and velocimeter saturate in some env."""
    sys, state, _, ours, _ = random_states
    for name, cutoff in (("clipped_vel", 0.5), ("imu_velocimeter", 0.3)):
        i = sys.sensor_names.index(name)
        values = ours[:, sys.sensor_adr[i]:sys.sensor_adr[i] + sys.sensor_dims[i]]
        assert np.abs(values).max() == cutoff, name
    shoulder_rate = state.qd[:, 6].numpy()  # after the free joint's 6
    np.testing.assert_array_equal(ours[:, slots(sys, "jointvel")[1]], np.clip(shoulder_rate, -0.5, 0.5))


def test_actuator_sensors_without_tendons():
    """Actuator sensors of a model without tendons (most models): a geared motor and a limited servo on hinges."""
    xml = """<mujoco><worldbody><body><joint name="a" axis="0 1 0"/>
      <geom type="capsule" size=".1" fromto="0 0 0 .3 0 0"/>
      <body pos=".3 0 0"><joint name="b" axis="1 0 0" ref=".2"/><geom type="capsule" size=".05" fromto="0 0 0 .2 0 0"/>
      </body></body></worldbody>
      <actuator><motor name="m" joint="a" gear="3"/><position name="p" joint="b" kp="20" forcerange="-1 1"/></actuator>
      <sensor><actuatorpos actuator="p"/><actuatorvel actuator="m"/><actuatorfrc actuator="m"/>
        <actuatorfrc actuator="p"/><jointactuatorfrc joint="a"/><jointactuatorfrc joint="b"/></sensor></mujoco>"""
    m, sys = mujoco.MjModel.from_xml_string(xml), torchsim.load_mjcf(xml, dtype=F64)
    rng = np.random.default_rng(2)
    q, qd, ctrl = rng.uniform(-1, 1, (ENVS, 2)), rng.normal(0, 1, (ENVS, 2)), rng.uniform(-1, 1, (ENVS, 2))
    state = torchsim.init(sys, torch.as_tensor(q), torch.as_tensor(qd))
    ours = torchsim.sensordata(sys, state, torch.as_tensor(ctrl)).numpy()
    np.testing.assert_allclose(ours, mujoco_sensordata(m, q, qd, ctrl), rtol=0, atol=1e-9)


def test_limit_sensors_read_the_side_within_its_margin(random_states):
    """Each env puts the shoulder or the slide within the margin of one side of its range (``SHOULDER_AND_SLIDE``):
    its limit sensors read MuJoCo's constraint distance less the margin and its rate, the other joint's read 0 (and
    ``test_sensor_type_matches_mujoco`` checks the values)."""
    sys, _, _, ours, _ = random_states
    shoulder, slide = (ours[:, slots(sys, "jointlimitpos")[k]] for k in (0, 1))
    np.testing.assert_allclose(shoulder, [-0.9 + 1 - 0.4, 1 - 0.85 - 0.4, 0, 0], atol=1e-12)
    np.testing.assert_allclose(slide, [0, 0, 0.2 - 0.19 - 0.05, -0.18 + 0.2 - 0.05], atol=1e-12)


def test_not_computed_types_warn_and_raise(random_states):
    """A type that needs the time (clock) and a delayed sensor load with one warning
    naming them; their slots are NaN, the dict leaves them out and reading one by name raises naming its type."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torchsim.load_mjcf(MODEL, dtype=F64)
    assert len(caught) == 1
    message = str(caught[0].message)
    assert all(re.search(f"{kind}.*{name!r}", message) for name, kind in NOT_COMPUTED.items()), message
    sys, state, ctrl, ours, _ = random_states
    by_name = torchsim.sensors_by_name(sys, state, ctrl)
    for name, kind in NOT_COMPUTED.items():
        i = sys.sensor_names.index(name)
        assert np.isnan(ours[:, sys.sensor_adr[i]:sys.sensor_adr[i] + sys.sensor_dims[i]]).all()
        assert name not in by_name
        with pytest.raises(torchsim.UnsupportedMJCFError, match=f"{name}.*{kind}"):
            torchsim.sensor(sys, state, name, ctrl)
    with pytest.raises(KeyError, match="no sensor 'nope'.*shoulder_pos"):
        torchsim.sensor(sys, state, "nope")
    assert len(by_name) == len(sys.sensor_names) - len(NOT_COMPUTED)


def test_sensors_on_mocap_bodies_are_not_computed():
    """A mocap body's pose is a System parameter the sensors do not read (yet): a sensor on it, or on a subtree or
    the model's weight that holds it, is named in the warning and raises, rather than reading the model pose."""
    xml = """<mujoco><worldbody>
      <body name="target" mocap="true" pos="0 0 1"><geom size=".1" contype="0" conaffinity="0"/><site name="s"/></body>
      <body><freejoint/><geom size=".1"/></body></worldbody>
      <sensor><framepos name="target_pos" objtype="site" objname="s"/><subtreecom name="all" body="world"/>
        <e_potential name="weight"/></sensor></mujoco>"""
    with pytest.warns(UserWarning, match="mocap") as caught:
        sys = torchsim.load_mjcf(xml, dtype=F64)
    state = torchsim.init(sys, torch.tensor([[0, 0, 1, 1, 0, 0, 0.0]], dtype=F64), torch.zeros(1, 6, dtype=F64))
    for name in ("target_pos", "all", "weight"):
        assert repr(name) in str(caught[0].message)
        with pytest.raises(torchsim.UnsupportedMJCFError, match=f"{name}.*mocap"):
            torchsim.sensor(sys, state, name)


def test_sensors_on_moving_cameras_are_not_computed():
    """A camera that tracks or targets (``mode`` other than ``fixed``) moves on its own: a frame sensor on it or
    relative to it, or an acceleration sensor on it, is named in the warning and raises; one on a fixed camera reads."""
    xml = """<mujoco><worldbody>
      <body><freejoint/><geom size=".1"/><camera name="fixed"/><camera name="tracking" mode="track"/></body>
      </worldbody><sensor><framepos name="on_fixed" objtype="camera" objname="fixed"/>
        <framepos name="on_tracking" objtype="camera" objname="tracking"/>
        <framepos name="relative_to_tracking" objtype="camera" objname="fixed" reftype="camera" refname="tracking"/>
        <framelinacc name="acc_on_tracking" objtype="camera" objname="tracking"/></sensor></mujoco>"""
    with pytest.warns(UserWarning, match="camera is not fixed to its body") as caught:
        sys = torchsim.load_mjcf(xml, dtype=F64)
    state = torchsim.init(sys, torch.tensor([[0, 0, 1, 1, 0, 0, 0.0]], dtype=F64), torch.zeros(1, 6, dtype=F64))
    for name in ("on_tracking", "relative_to_tracking", "acc_on_tracking"):
        assert repr(name) in str(caught[0].message)
        with pytest.raises(torchsim.UnsupportedMJCFError, match=name):
            torchsim.sensor(sys, state, name)
    assert "'on_fixed'" not in str(caught[0].message)
    np.testing.assert_allclose(torchsim.sensor(sys, state, "on_fixed").numpy(), [[0, 0, 1]], atol=1e-12)


def test_reading_by_name(random_states):
    """One sensor by name and the dict of all are slices of ``sensordata``; a sensor that does not read actuator
    forces needs no controls, one that does names what it needs."""
    sys, state, ctrl, ours, _ = random_states
    by_name = torchsim.sensors_by_name(sys, state, ctrl)
    for name in ("tip_pos", "neck_quat", "servo_frc", "world_subtree"):
        i = sys.sensor_names.index(name)
        expected = ours[:, sys.sensor_adr[i]:sys.sensor_adr[i] + sys.sensor_dims[i]]
        np.testing.assert_array_equal(torchsim.sensor(sys, state, name, ctrl).numpy(), expected)
        np.testing.assert_array_equal(by_name[name].numpy(), expected)
    assert torchsim.sensor(sys, state, "imu_gyro").shape == (ENVS, 3)
    with pytest.raises(ValueError, match="actuatorfrc.*pass ctrl"):
        torchsim.sensor(sys, state, "servo_frc")
    with pytest.raises(ValueError, match="actuatorfrc.*pass ctrl"):
        torchsim.sensordata(sys, state)


def test_sensors_are_differentiable(random_states):
    """Gradients flow from every computed sensor to the State's poses and velocities (checked against finite
    differences in float64)."""
    sys, state, ctrl, _, _ = random_states
    computed = [a for kind in COMPUTED for a in slots(sys, kind)]

    first = torchsim.State(*(x[:1] for x in state))

    def read(x_pos, x_quat, xd_vel, xd_ang):
        moved = first._replace(x_pos=x_pos, x_quat=x_quat, xd_vel=xd_vel, xd_ang=xd_ang)
        # the accelerometer (tests/test_accel_sensors.py) reads the given next State rather than stepping each call
        return torchsim.sensordata(sys, moved, ctrl[:1], next_state=moved)[:, computed]

    inputs = tuple(x.clone().requires_grad_() for x in first[:4])
    assert torch.autograd.gradcheck(read, inputs)


def test_model_without_sensors():
    """A model without sensors reads an empty sensordata."""
    sys = torchsim.load_mjcf(PENDULUM, dtype=F64)
    state = torchsim.init(sys, torch.zeros(2, 1, dtype=F64), torch.zeros(2, 1, dtype=F64))
    assert sys.sensor_groups == () and torchsim.sensordata(sys, state).shape == (2, 0)
