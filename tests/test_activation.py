"""Actuator activation dynamics (MuJoCo's ``dyntype``, ``torchsim.activation``): ``State.act`` against MuJoCo's
``data.act``, the forces it drives against ``actuator_force``, a driven arm's path against MuJoCo's, and the
strategies and steppers that carry it."""

import re
import warnings

import mujoco
import numpy as np
import pytest
import torch

import torchsim
import torchsim.sensors
from torchsim import activation, actuators, lanes
from torchsim.envs.base import select_state
from torchsim.execution.mujoco import MujocoStepper
from torchsim.io_mjcf import UnsupportedMJCFError, load_mjcf

#: A two-link arm swinging in the x-z plane under gravity, one actuator of every dyntype (and actearly, actlimited,
#: muscle dynamics with and without smoothing) and one without dynamics.
ARM = """
<mujoco><option timestep="{dt}"/>
  <worldbody>
    <body name="upper" pos="0 0 1"><joint name="shoulder" type="hinge" axis="0 1 0" damping="0.05"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="1"/>
      <body name="lower" pos="0.3 0 0"><joint name="elbow" type="hinge" axis="0 1 0" damping="0.05"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="0.5"/></body>
    </body>
  </worldbody>
  <actuator>
    <general joint="shoulder" dyntype="integrator" gainprm="4" actlimited="true" actrange="-1 1" ctrlrange="-5 5"
             ctrllimited="true"/>
    <general joint="elbow" dyntype="filter" dynprm="0.05" gainprm="3" biastype="affine" biasprm="0 -1 -0.2"/>
    <general joint="elbow" dyntype="filterexact" dynprm="0.03" gainprm="1" actearly="true"/>
    <general joint="shoulder" dyntype="muscle" dynprm="0.01 0.04 0.3" gainprm="-5"/>
    <general joint="elbow" dyntype="muscle" dynprm="0.02 0.05 0" gainprm="2" actearly="true"/>
    <motor joint="shoulder" gear="0.5" ctrlrange="-1 1" ctrllimited="true"/>
  </actuator>
</mujoco>"""
DT = 0.002


def _ctrl(t: float) -> np.ndarray:
    """Controls at time ``t`` [s]: past the ranges at times (the integrator's ctrlrange, the muscles' [0, 1])."""
    return np.array([6 * np.sin(7 * t), np.cos(5 * t), np.sin(11 * t), 0.5 + 0.7 * np.sin(9 * t),
                     0.5 + 0.7 * np.cos(13 * t), 1.5 * np.sin(3 * t)])


def _mujoco_path(xml: str, steps: int, split: int = 1, control=_ctrl):
    """MuJoCo's ``qpos`` and ``act`` after each of ``steps`` steps of ``DT`` under :func:`_ctrl`, each step as
    ``split`` steps of ``DT / split`` with the control held."""
    m = mujoco.MjModel.from_xml_string(xml.format(dt=DT / split))
    d = mujoco.MjData(m)
    qpos, act = [], []
    for k in range(steps):
        d.ctrl[:] = control(k * DT)
        for _ in range(split):
            mujoco.mj_step(m, d)
        qpos.append(d.qpos.copy())
        act.append(d.act.copy())
    return np.array(qpos), np.array(act)


def _torchsim_path(xml: str, steps: int, control=_ctrl):
    sys = load_mjcf(xml.format(dt=DT), dtype=torch.float64)
    state = torchsim.init(sys, sys.q0[None], torch.zeros(1, sys.nv, dtype=torch.float64))
    qpos, act = [], []
    for k in range(steps):
        state = torchsim.step(sys, state, torch.as_tensor(control(k * DT))[None])
        qpos.append(state.q[0].numpy())
        act.append(state.act[0].numpy())
    return np.array(qpos), np.array(act)


def test_act_is_mujocos_act():
    """Every dyntype's activation after each of 200 steps equals MuJoCo's ``data.act`` to float64 rounding: the
    update is MuJoCo's arithmetic on the same controls and activations (the arm's motion plays no part)."""
    _, ours = _torchsim_path(ARM, 200)
    _, theirs = _mujoco_path(ARM, 200)
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-12)
    assert (theirs[:, 0] == 1.0).any()  # the integrator reached its actrange: the clamp was exercised


def test_force_is_driven_by_act():
    """``actuator_force`` at a state with activations equals MuJoCo's: ``gain * act + bias`` for the activated
    actuators (with actearly, the activation the step ends at), ``gain * clamped ctrl`` for the motor."""
    xml = ARM.format(dt=DT)
    m, d = mujoco.MjModel.from_xml_string(xml), mujoco.MjData(mujoco.MjModel.from_xml_string(xml))
    sys = load_mjcf(xml, dtype=torch.float64)
    rng = np.random.default_rng(0)
    for _ in range(3):
        d.qpos[:], d.qvel[:] = rng.uniform(-1, 1, m.nq), rng.normal(size=m.nv)
        d.act[:], d.ctrl[:] = rng.uniform(-1.5, 1.5, m.na), rng.uniform(-2, 2, m.nu)
        mujoco.mj_forward(m, d)
        q, qd = (lanes.to_lanes(torch.as_tensor(x)[None]) for x in (d.qpos, d.qvel))
        ctrl, act = (lanes.to_lanes(torch.as_tensor(x)[None]) for x in (d.ctrl, d.act))
        np.testing.assert_allclose(activation.rates(sys, ctrl, act)[:, 0].numpy(), d.act_dot, rtol=0, atol=1e-9)
        force = actuators.forces(sys, *actuators.coordinates(sys, q, qd), activation.drive(sys, ctrl, act)[0])
        np.testing.assert_allclose(force[:, 0].numpy(), d.actuator_force, rtol=0, atol=1e-12)


def test_force_sensors_read_act():
    """``actuatorfrc`` and ``jointactuatorfrc`` sensors of activated actuators read the force their activations drive,
    as MuJoCo's ``sensordata`` does."""
    xml = ARM.format(dt=DT).replace("</actuator>", """</actuator>
  <sensor>
    <actuatorfrc actuator="filtered"/><actuatorfrc actuator="early"/><jointactuatorfrc joint="elbow"/>
  </sensor>""")
    xml = xml.replace('dyntype="filter"', 'name="filtered" dyntype="filter"').replace(
        'dyntype="filterexact"', 'name="early" dyntype="filterexact"')
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:], d.act[:], d.ctrl[:] = [0.3, -0.4], [1.0, -2.0], [0.5, 0.2, -0.3, 0.6, 0.4], _ctrl(0.1)
    mujoco.mj_forward(m, d)
    sys = load_mjcf(xml, dtype=torch.float64)
    state = torchsim.init(sys, torch.as_tensor(d.qpos)[None], torch.as_tensor(d.qvel)[None],
                          torch.as_tensor(d.act)[None])
    ours = torchsim.sensors.sensordata(sys, state, torch.as_tensor(d.ctrl)[None])
    np.testing.assert_allclose(ours[0].numpy(), d.sensordata, rtol=0, atol=1e-12)


#: The arm moved by MuJoCo muscles: a flexor and an extensor on each joint (moment arms of either sign), within
#: joint ranges that set their length ranges; one with its peak force from ``scale / acc0`` (force -1), one with a
#: smoothed activation, and a <general> muscle gain without passive bias.
MUSCLES = ARM.split("<actuator>")[0].replace('damping="0.05"/>', 'damping="0.05" range="-80 80"/>') + """<actuator>
    <muscle joint="shoulder" gear="0.1" force="8"/>
    <muscle joint="shoulder" gear="-0.1" force="-1" scale="5" lmin="0.6" lmax="1.5" vmax="2" fpmax="0.8"/>
    <muscle joint="elbow" gear="0.05" force="6" tausmooth="0.2"/>
    <muscle joint="elbow" gear="-0.06" force="6" range="0.7 1.1" fvmax="1.6"/>
    <general joint="elbow" dyntype="muscle" dynprm="0.01 0.04" gaintype="muscle"
             gainprm="0.75 1.05 4 200 0.5 1.6 1.5 1.3 1.2" gear="0.04"/>
  </actuator>
</mujoco>"""


def _muscle_ctrl(t: float) -> np.ndarray:
    return 0.5 + 0.6 * np.sin(np.array([4, 5, 6, 7, 8]) * t + np.arange(5))


def test_muscle_forces_are_mujocos():
    """MuJoCo's muscle gain and bias (force-length-velocity curves): ``actuator_force`` at random joint angles and
    speeds (lengths across each muscle's range, speeds past ``vmax`` both ways) and activations equals MuJoCo's."""
    xml = MUSCLES.format(dt=DT)
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    sys = load_mjcf(xml, dtype=torch.float64)
    rng = np.random.default_rng(2)
    for _ in range(20):
        d.qpos[:], d.qvel[:] = rng.uniform(-1.6, 1.6, m.nq), rng.normal(scale=20, size=m.nv)
        d.act[:], d.ctrl[:] = rng.uniform(0, 1, m.na), rng.uniform(-0.5, 1.5, m.nu)
        mujoco.mj_forward(m, d)
        q, qd = (lanes.to_lanes(torch.as_tensor(x)[None]) for x in (d.qpos, d.qvel))
        ctrl, act = (lanes.to_lanes(torch.as_tensor(x)[None]) for x in (d.ctrl, d.act))
        force = actuators.forces(sys, *actuators.coordinates(sys, q, qd), activation.drive(sys, ctrl, act)[0])
        np.testing.assert_allclose(force[:, 0].numpy(), d.actuator_force, rtol=1e-12, atol=1e-12)


def test_muscle_path_against_mujoco():
    """The arm moved by its muscles (and falling onto its joint limits) for 0.5 s follows MuJoCo's path within 1.5x
    MuJoCo's own dt vs dt/4 difference (measured: 1.07x, 0.012 rad). Without the muscles' excitation its path is
    over 10x that far from this one: the bound tests the muscles."""
    steps = 250
    theirs, _ = _mujoco_path(MUSCLES, steps, control=_muscle_ctrl)
    finer, _ = _mujoco_path(MUSCLES, steps, split=4, control=_muscle_ctrl)
    ours, _ = _torchsim_path(MUSCLES, steps, control=_muscle_ctrl)
    own_error, error = np.abs(theirs - finer).max(), np.abs(ours - theirs).max()
    assert error < 1.5 * own_error, (error, own_error)
    idle, _ = _mujoco_path(MUSCLES, steps, control=lambda t: np.zeros(5))
    assert np.abs(idle - theirs).max() > 10 * own_error


def test_path_against_mujoco():
    """The arm driven through its activations for 0.5 s follows MuJoCo's path as closely as MuJoCo's own path with a
    4x finer step does: torchsim's joint angles are within 2x MuJoCo's dt vs dt/4 difference of MuJoCo's (measured
    0.020 rad against 0.014 rad, 1.4x). Read with the controls as the activations (dyntype none), the same arm ends
    several times farther off: the bound does test the activations."""
    steps = 250
    theirs, _ = _mujoco_path(ARM, steps)
    finer, _ = _mujoco_path(ARM, steps, split=4)
    ours, _ = _torchsim_path(ARM, steps)
    own_error = np.abs(theirs - finer).max()
    error = np.abs(ours - theirs).max()
    assert error < 2 * own_error, (error, own_error)
    undriven, _ = _torchsim_path(re.sub(r' (dyntype|dynprm|actearly|actlimited|actrange)="[^"]*"', "", ARM), steps)
    assert np.abs(undriven - theirs).max() > 5 * error


def test_mujoco_stepper_carries_act():
    """``MujocoStepper`` hands MuJoCo's activations on through ``State.act``: its path is MuJoCo's own."""
    xml = ARM.format(dt=DT)
    sys, model = load_mjcf(xml, dtype=torch.float64), mujoco.MjModel.from_xml_string(xml)
    stepper = MujocoStepper(sys, model, threads=1)
    state = torchsim.init(sys, sys.q0[None], torch.zeros(1, sys.nv, dtype=torch.float64))
    for k in range(50):
        state = stepper(state, torch.as_tensor(_ctrl(k * DT))[None])
    qpos, act = _mujoco_path(ARM, 50)
    np.testing.assert_allclose(state.act[0].numpy(), act[-1], rtol=0, atol=1e-12)
    np.testing.assert_allclose(state.q[0].numpy(), qpos[-1], rtol=0, atol=1e-9)


def test_strategies_carry_act():
    """A model with activations does not run on the step kernel (which carries no ``act``): the Stepper falls back
    to ``loop`` with one warning naming the reason, and its steps (the compiled graphs run op by op) equal the
    reference step's, activations included. Two envs from different activations stay apart."""
    sys = load_mjcf(ARM.format(dt=DT), dtype=torch.float64)
    stepper = torchsim.Stepper(sys, backend="aot_eager")
    with pytest.warns(UserWarning, match="does not carry actuator activations"):
        stepper.build()
    assert stepper.strategy == "loop"
    act = torch.tensor([[0.2, -0.1, 0.3, 0.5, 0.1], [0.0] * 5], dtype=torch.float64)
    ours = reference = torchsim.init(sys, sys.q0.expand(2, -1), torch.zeros(2, sys.nv, dtype=torch.float64), act)
    for k in range(3):
        ctrl = torch.as_tensor(_ctrl(k * DT)).expand(2, -1)
        ours, reference = stepper(ours, ctrl), torchsim.step(sys, reference, ctrl)
    for a, b in zip(ours, reference):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
    assert not torch.allclose(ours.act[0], ours.act[1])


def test_models_without_activations_carry_an_empty_act():
    """A model without activation dynamics has ``na == 0`` and an empty ``(B, 0)`` act that every step and reset
    passes on."""
    sys = load_mjcf(ARM.format(dt=DT).split("<actuator>")[0] + "</mujoco>")
    state = torchsim.init(sys, sys.q0.expand(3, -1), torch.zeros(3, sys.nv))
    assert sys.na == 0 and state.act.shape == (3, 0)
    after = torchsim.step(sys, state, torch.zeros(3, 0))
    assert after.act.shape == (3, 0)
    assert select_state(torch.tensor([True, False, True]), after, state).act.shape == (3, 0)


def test_reset_restores_act():
    """A partial reset (``envs.base.select_state``) puts the chosen envs' activations back with their poses."""
    sys = load_mjcf(ARM.format(dt=DT), dtype=torch.float64)
    start = torchsim.init(sys, sys.q0.expand(2, -1), torch.zeros(2, sys.nv, dtype=torch.float64))
    moved = torchsim.step(sys, start, torch.ones(2, sys.nu, dtype=torch.float64))
    assert (moved.act != 0).any(-1).all()
    mixed = select_state(torch.tensor([True, False]), start, moved)
    assert (mixed.act[0] == 0).all() and torch.equal(mixed.act[1], moved.act[1])


def test_bad_act_is_refused():
    sys = load_mjcf(ARM.format(dt=DT), dtype=torch.float64)
    with pytest.raises(ValueError, match=r"act must have shape \(2, 5\)"):
        torchsim.init(sys, sys.q0.expand(2, -1), torch.zeros(2, sys.nv, dtype=torch.float64),
                      torch.zeros(2, 4, dtype=torch.float64))


@pytest.mark.parametrize("actuator, refusal", [
    ('<general joint="shoulder" gaintype="affine"/>', "only fixed or muscle gain"),
    ('<general joint="shoulder" dyntype="user"/>', "activation dynamics"),
])
def test_refusals_name_the_feature(actuator, refusal):
    xml = ARM.format(dt=DT).split("<actuator>")[0] + f"<actuator>{actuator}</actuator></mujoco>"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # MuJoCo's own warnings on the user dyntype
        with pytest.raises(UnsupportedMJCFError, match=refusal):
            load_mjcf(xml)
