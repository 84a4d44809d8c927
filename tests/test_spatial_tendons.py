"""Spatial tendons against MuJoCo: path lengths and rates through sites and pulleys, their springs, dampers and
actuators as forces on the sites' bodies, and a ball hanging on a string (a limited spatial tendon)."""

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from torchsim import actuators, lanes, tendon_paths, tendons
from torchsim.execution.kernel import emit_cuda
from torchsim.execution.kernel.step import StepKernel
from torchsim.kinematics import dof_values, joint_frames, with_world
from models import F64
from test_strategies import STEPS, _check_against_reference

# A two-link arm (hinges h1, h2, the second about a tilted axis) and a free ball, touching nothing: "cable" runs from
# a world site over both links; "sling" from the forearm to the ball, then over a pulley (divisor 2) from the ball to
# a world hook; "coupling" is a fixed tendon beside them. {tendon} options and {actuator}s are filled in.
ARM_AND_BALL = """
<mujoco>
  <option timestep="{dt}"/>
  <default><geom contype="0" conaffinity="0"/></default>
  <worldbody>
    <site name="anchor" pos="0 0 1.5"/>
    <site name="hook" pos="0.5 0 1.6"/>
    <body name="arm" pos="0 0 1"><joint name="h1" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 .4 0 0" size=".03"/>
      <site name="arm" pos=".3 .05 0"/>
      <body name="fore" pos=".4 0 0"><joint name="h2" type="hinge" axis="0 .6 .8"/>
        <geom type="capsule" fromto="0 0 0 .3 0 0" size=".03"/>
        <site name="fore" pos=".25 0 .02"/>
      </body>
    </body>
    <body name="ball" pos=".6 .2 .8"><freejoint/>
      <geom type="sphere" size=".05"/>
      <site name="ball" pos=".02 0 .03"/>
    </body>
  </worldbody>
  <tendon>
    <spatial name="cable" {cable}>
      <site site="anchor"/><site site="arm"/><site site="fore"/>
    </spatial>
    <spatial name="sling" {sling}>
      <site site="fore"/><site site="ball"/>
      <pulley divisor="2"/>
      <site site="ball"/><site site="hook"/>
    </spatial>
    <fixed name="coupling"><joint joint="h1" coef="1"/><joint joint="h2" coef="-.5"/></fixed>
  </tendon>
  <actuator>{actuator}</actuator>
</mujoco>
"""
SPRINGS = dict(cable='stiffness="50" springlength=".2 .3" damping="2"', sling='stiffness="20" damping="1"')


def arm_and_ball(actuator: str = "", dt: float = 0.002, **tendon) -> str:
    return ARM_AND_BALL.format(dt=dt, actuator=actuator, **({"cable": "", "sling": ""} | tendon))


def random_states(m: mujoco.MjModel, count: int, seed: int):
    """MuJoCo data at ``count`` random poses and velocities (ball quaternions normalised), forward-evaluated."""
    rng = np.random.default_rng(seed)
    d = mujoco.MjData(m)
    for _ in range(count):
        d.qpos[:] = m.qpos0 + rng.uniform(-1, 1, m.nq) * 0.5
        d.qpos[5:9] /= np.linalg.norm(d.qpos[5:9])
        d.qvel[:], d.ctrl[:] = rng.normal(size=m.nv), rng.uniform(-1, 1, m.nu)
        mujoco.mj_forward(m, d)
        yield d


def lanes_bodies(sys: torchsim.System, d: mujoco.MjData):
    """torchsim's ext bodies (lanes) at MuJoCo's ``qpos``/``qvel``, and its hinge coordinates and rates ``(D, 1)``."""
    state = torchsim.init(sys, torch.as_tensor(d.qpos)[None], torch.as_tensor(d.qvel)[None])
    bodies = with_world(*(lanes.to_lanes(x, 1) for x in state[:4]))
    return bodies, torch.as_tensor(d.qpos)[sys.dof_qpos][:, None], torch.as_tensor(d.qvel)[sys.dof_qvel][:, None]


def generalized(m: mujoco.MjModel, d: mujoco.MjData, force: torch.Tensor, torque: torch.Tensor) -> np.ndarray:
    """MuJoCo's generalized force ``(nv,)`` of torchsim's body wrenches ``(3, N + 1, 1)`` (force at each body's
    COM, torque): ``J_p^T f + J_r^T t`` with MuJoCo's COM Jacobians (torchsim body ``i`` is MuJoCo body ``i + 1``:
    these models fuse no bodies)."""
    jacp, jacr, total = np.zeros((3, m.nv)), np.zeros((3, m.nv)), np.zeros(m.nv)
    for i in range(m.nbody - 1):
        mujoco.mj_jacBodyCom(m, d, jacp, jacr, i + 1)
        total += jacp.T @ force[:, i, 0].numpy() + jacr.T @ torque[:, i, 0].numpy()
    return total


def test_lengths_and_rates_match_mujoco():
    xml = arm_and_ball()
    m, sys = mujoco.MjModel.from_xml_string(xml), torchsim.load_mjcf(xml, dtype=F64)
    assert sys.ten_spatial and sys.ten_seg_tendon.tolist() == [0, 0, 1, 1]
    assert sys.ten_seg_scale.tolist() == [1.0, 1.0, 1.0, 0.5]
    for d in random_states(m, 5, seed=0):
        path = tendon_paths.paths(sys, lanes_bodies(sys, d)[0])
        np.testing.assert_allclose(path.length[:2, 0].numpy(), d.ten_length[:2], rtol=0, atol=1e-12)
        np.testing.assert_allclose(path.velocity[:2, 0].numpy(), d.ten_velocity[:2], rtol=0, atol=1e-12)
        assert path.length[2, 0] == 0  # the fixed tendon's length is torchsim.tendons.lengths'


def test_passive_and_actuator_forces_match_mujoco():
    """Springs (``cable``'s dead band), dampers, a motor and a servo on the spatial tendons and a joint motor: the
    body forces torchsim applies do the generalized work of MuJoCo's ``qfrc_passive + qfrc_actuator``."""
    actuator = """<motor tendon="sling" gear="2" ctrlrange="-1 1" ctrllimited="true"/>
      <position tendon="cable" kp="30" kv="3" gear="1.5"/>
      <motor joint="h2" gear="3"/>"""
    xml = arm_and_ball(actuator, **SPRINGS)
    m, sys = mujoco.MjModel.from_xml_string(xml), torchsim.load_mjcf(xml, dtype=F64)
    for d in random_states(m, 5, seed=1):
        bodies, q, qd = lanes_bodies(sys, d)
        axes = dof_values(sys, joint_frames(sys, bodies).axes)
        force, torque = actuators.body_wrench(sys, bodies, axes, q, qd, torch.as_tensor(d.ctrl)[:, None])
        assert abs(d.qfrc_passive).max() > 1 and abs(d.qfrc_actuator).max() > 1
        np.testing.assert_allclose(generalized(m, d, force, torque), d.qfrc_passive + d.qfrc_actuator,
                                   rtol=0, atol=1e-10)


def test_sensors_match_mujoco():
    """Tendon, actuator, limit and energy sensors on spatial tendons read MuJoCo's ``sensordata``; a joint's actuator
    force, which a spatial tendon's actuator exerts through bodies, is not computed (and says why)."""
    actuator = '<position name="servo" tendon="cable" kp="30" kv="3" gear="1.5"/><motor joint="h1"/>'
    sensors = """<sensor><tendonpos tendon="sling"/><tendonvel tendon="cable"/><actuatorpos actuator="servo"/>
      <actuatorvel actuator="servo"/><actuatorfrc actuator="servo"/><tendonactuatorfrc tendon="cable"/>
      <tendonlimitpos tendon="sling"/><tendonlimitvel tendon="sling"/><e_potential/>
      <jointactuatorfrc name="h1_force" joint="h1"/></sensor>"""
    xml = arm_and_ball(actuator, sling='limited="true" range="0 .7" margin="1"', cable=SPRINGS["cable"])
    xml = xml.replace("</mujoco>", sensors + "</mujoco>")
    m = mujoco.MjModel.from_xml_string(xml)
    with pytest.warns(UserWarning, match="h1_force"):
        sys = torchsim.load_mjcf(xml, dtype=F64)
    assert "spatial tendon" in sys.sensor_skipped[-1]
    for d in random_states(m, 3, seed=3):
        state = torchsim.init(sys, torch.as_tensor(d.qpos)[None], torch.as_tensor(d.qvel)[None])
        ours = torchsim.sensordata(sys, state, torch.as_tensor(d.ctrl)[None])[0].numpy()
        np.testing.assert_allclose(ours[:-1], d.sensordata[:-1], rtol=0, atol=1e-12)
        assert d.sensordata[6] != 0  # the sling is within its limit's margin

def test_unsupported_spatial_features_are_named():
    wrapped = arm_and_ball().replace('<site site="anchor"/><site site="arm"/>',
                                     '<site site="anchor"/><geom geom="upper"/><site site="arm"/>')
    wrapped = wrapped.replace('<geom type="capsule" fromto="0 0 0 .4 0 0"', '<geom name="upper" type="cylinder" '
                              'fromto="0 0 0 .4 0 0"')
    with pytest.raises(torchsim.UnsupportedMJCFError, match="tendon 'cable': wrapping around geom 'upper'"):
        torchsim.load_mjcf(wrapped)
    equal = arm_and_ball().replace("</tendon>", '</tendon><equality><tendon tendon1="sling"/></equality>')
    with pytest.raises(torchsim.UnsupportedMJCFError, match="tendon 'sling': equality constraints on spatial"):
        torchsim.load_mjcf(equal)
    with pytest.raises(ValueError, match="spatial tendons.*body_wrench"):
        actuators.dof_forces(torchsim.load_mjcf(arm_and_ball(), dtype=F64), torch.zeros(2, 1, dtype=F64),
                             torch.zeros(2, 1, dtype=F64), torch.zeros(0, 1, dtype=F64))


# ball_in_cup's string: a ball on two slides hangs by a spatial tendon limited to 0.3 m (its default solref and
# solimp) from a cup, {cup}: on two sprung and heavily damped slides, as in ball_in_cup, or fixed. The ball starts
# 0.2 m out to the side with the string nearly taut (0.298 m), and swings.
BALL_ON_STRING = """
<mujoco>
  <option timestep="{dt}"/>
  <default><geom contype="0" conaffinity="0"/></default>
  <worldbody>
    <body name="cup" pos="0 0 .6">{cup}
      <geom type="capsule" fromto="-.05 0 0 .05 0 0" size=".008"/><site name="cup" pos="0 0 -.108"/>
    </body>
    <body name="ball" pos="0 0 .2"><joint name="ball_x" type="slide" axis="1 0 0"/>
      <joint name="ball_z" type="slide" axis="0 0 1"/>
      <geom type="sphere" size=".025"/><site name="ball"/>
    </body>
  </worldbody>
  <tendon><spatial name="string" limited="true" range="0 .3"><site site="ball"/><site site="cup"/></spatial></tendon>
</mujoco>"""
CUPS = {"sprung": """<joint name="cup_x" type="slide" axis="1 0 0" damping="3" stiffness="20"/>
      <joint name="cup_z" type="slide" axis="0 0 1" damping="3" stiffness="20"/>""", "fixed": ""}
BALL_OUT = np.array([0.2, 0.07])
STRING_STEP = 0.002


def ball_on_string(cup: str, dt: float = STRING_STEP) -> str:
    return BALL_ON_STRING.format(dt=dt, cup=CUPS[cup])


def mujoco_swing(xml: str, seconds: float, substeps: int = 1):
    """MuJoCo's ``qpos`` and string length after each ``STRING_STEP``, stepping at the model's timestep."""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    d.qpos[-2:] = BALL_OUT
    q, length = [], []
    for _ in range(round(seconds / STRING_STEP)):
        for _ in range(substeps):
            mujoco.mj_step(m, d)
        q.append(d.qpos.copy())
        length.append(d.ten_length[0])
    return np.array(q), np.array(length)


@pytest.mark.parametrize("method", ["spring", "xpbd"])
@pytest.mark.parametrize("cup", ["fixed", "sprung"])
def test_ball_on_string_swings_like_mujoco(cup, method):
    """1 s of the swing, torchsim (2 ms steps of 4 substeps) against MuJoCo at 0.5 ms. With slides alone the
    string's tendon inverse inertia is ``tendon_invweight0`` everywhere and ``a0`` holds every other force, so the
    limit is MuJoCo's force exactly (``tendon_paths.limit_wrench``): the paths agree to rounding (measured 1e-12),
    except with the spring method's sprung cup, whose joint springs hold its rotation, which the string's pull at the
    site 0.108 m below its COM twists: 2.6 mm off, 2.4x MuJoCo's own 2 ms against 0.5 ms (1.07 mm). The string
    stretches 2.6 mm past its limit in MuJoCo; without ``a0`` (the fixed tendons' explicit limit) it stretched 23 mm."""
    fine, length = mujoco_swing(ball_on_string(cup, STRING_STEP / 4), 1.0, substeps=4)
    sys = torchsim.load_mjcf(ball_on_string(cup), dtype=F64, method=method)
    assert sys.ten_path_limits and not sys.ten_limits and not tendons.active(sys)
    q0 = np.r_[np.zeros(sys.nq - 2), BALL_OUT]  # the cup, if sprung, at rest at its springs' zero
    state = torchsim.init(sys, torch.as_tensor(q0)[None], torch.zeros(1, sys.nv, dtype=F64))
    ours = []
    for _ in range(len(fine)):
        state = torchsim.step(sys, state, torch.zeros(1, 0, dtype=F64))
        ours.append(state.q[0].numpy().copy())
    error = np.abs(np.array(ours) - fine).max()
    assert length.max() > 0.3 + 1e-3 and np.ptp(fine[:, -2]) > 0.3  # the string holds the ball, which swings
    if cup == "sprung" and method == "spring":
        coarse, _ = mujoco_swing(ball_on_string(cup), 1.0)
        assert error < 3 * np.abs(coarse - fine).max(), (error, np.abs(coarse - fine).max())
    else:
        assert error < 1e-10, error


ACTUATED_ARM = arm_and_ball('<position tendon="sling" kp="30" kv="3"/><motor tendon="cable" gear="2"/>', **SPRINGS)


@pytest.mark.parametrize("strategy", ["kernel", "cuda"])
@pytest.mark.parametrize("model", ["arm", "string"])
def test_compiled_step_agrees_with_reference(model, strategy, monkeypatch, tmp_path):
    """The generated step (the C++ kernel, and the CUDA C one built for the host) swings the arm on its springs and
    actuated spatial tendons, and the ball on its string (swung out, so that the string's limit pulls), like the
    reference step, by ``tests/test_strategies.py``'s bound: float64, 2 envs."""
    monkeypatch.setenv("TORCHSIM_CACHE_DIR", str(tmp_path))
    sys = torchsim.load_mjcf(ACTUATED_ARM if model == "arm" else ball_on_string("sprung"), dtype=F64)
    q0 = sys.q0.expand(2, -1).clone()
    generator = torch.Generator().manual_seed(0)
    qd0 = torch.randn(2, sys.nv, generator=generator, dtype=F64)
    if model == "string":  # the ball out and moving outwards: the string pulls in both envs within the 20 steps
        q0[:, -2:] = torch.as_tensor(BALL_OUT)
        qd0[:, -2:] = torch.tensor([[0.5, 0.0], [1.0, 0.0]], dtype=F64)
    start = torchsim.init(sys, q0, qd0)
    ctrl = torch.rand(STEPS, 2, sys.nu, generator=generator, dtype=F64)
    if strategy == "kernel":
        stepper = torchsim.Stepper(sys, "kernel")
        assert stepper.strategy == "kernel"
    else:
        kernel = StepKernel(sys, emitter=emit_cuda)
        stepper = lambda state, ctrl: kernel(sys, state, ctrl)  # noqa: E731
    _check_against_reference(f"spatial tendons {strategy}", sys, stepper, start, ctrl, 2, min_move=1e-3)
