"""Acceleration and constraint-force sensors (``accelerometer``, ``framelinacc``, ``frameangacc``, ``force``,
``torque``) against MuJoCo 4.0's ``sensordata``.

torchsim reads the mean acceleration over the next step where MuJoCo reads the instantaneous one at the step's
start (``torchsim.sensors``): resting scenes are compared after both engines settled, moving ones at the same
``qpos, qvel`` within MuJoCo's own change of each value over one step from there."""

import warnings

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from models import F64

#: A box resting on a plane (turned 30 deg about z), an IMU site on it, and a payload welded on top (a sphere that
#: collides with nothing) with a mount site: the payload's force and torque are its weight carried by the weld; the
#: box's own force sensor reads what its free joint carries, 0, once the floor's contact forces are subtracted.
BOX = """
<mujoco><option timestep="0.002"/><worldbody><geom type="plane" size="5 5 .1"/>
  <body name="box" pos="0 0 0.05" euler="0 0 30"><freejoint/><geom type="box" size="0.2 0.1 0.05" mass="2"/>
    <site name="imu" pos="0.1 0.05 0.02" euler="20 -10 40"/>
    <body name="payload" pos="0.05 0 0.1" euler="10 0 0">
      <geom type="sphere" size="0.05" mass="0.5" contype="0" conaffinity="0"/>
      <site name="mount" pos="0.02 0 -0.05" euler="0 30 0"/></body></body>
</worldbody>
<sensor><accelerometer name="imu_acc" site="imu"/><framelinacc name="imu_linacc" objtype="site" objname="imu"/>
  <frameangacc name="box_angacc" objtype="body" objname="box"/><force name="mount_force" site="mount"/>
  <torque name="mount_torque" site="mount"/><force name="box_force" site="imu"/></sensor></mujoco>"""

#: A 0.5 m pendulum (rod and bob) on a hinge about y, 1 ms: sites (turned) at the pivot and the bob.
PENDULUM = """
<mujoco><option timestep="0.001"/><worldbody>
  <body name="rod" pos="0 0 1"><joint type="hinge" axis="0 1 0"/>
    <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.02" mass="0.3"/>
    <geom type="sphere" pos="0 0 -0.5" size="0.05" mass="1"/>
    <site name="pivot" euler="0 0 20"/><site name="bob" pos="0 0 -0.5" euler="30 0 0"/>
  </body></worldbody>
<sensor><accelerometer site="bob"/><framelinacc objtype="site" objname="bob"/>
  <frameangacc objtype="body" objname="rod"/><framelinacc objtype="xbody" objname="rod"/>
  <force site="pivot"/><torque site="pivot"/><force site="bob"/><torque site="bob"/></sensor></mujoco>"""

#: A lever hinged above a frictionless floor, its far end resting on it, with a tool welded to it: the hinge carries
#: the part of the weight the floor does not (a contact inside the hip sensor's subtree), the weld the tool's.
#: Frictionless: with friction the split of the horizontal force between hinge and floor is indeterminate.
LEVER = """
<mujoco><option timestep="0.002"/><worldbody><geom type="plane" size="5 5 .1" friction="0 0.005 0.0001"/>
  <body name="link" pos="0 0 0.3"><joint type="hinge" axis="0 1 0" damping="0.5"/>
    <geom type="capsule" fromto="0 0 0 0.6 0 -0.25" size="0.03" mass="1" friction="0 0.005 0.0001"/>
    <site name="hip" euler="0 20 10"/>
    <body name="tool" pos="0.3 0 -0.125" euler="0 0 40">
      <geom type="box" size="0.05 0.04 0.03" mass="0.4" contype="0" conaffinity="0"/>
      <site name="wrist" pos="0 0 0.03"/></body></body>
</worldbody>
<sensor><force name="hip_force" site="hip"/><torque name="hip_torque" site="hip"/><force site="wrist"/>
  <torque site="wrist"/><accelerometer site="wrist"/></sensor></mujoco>"""

#: A free box with principal inertias 1 : 2 : 4 tumbling (started spinning about all three axes) as it falls;
#: nothing to touch. A site off its centre reads the centripetal acceleration, the body Euler's equations.
TUMBLER = """
<mujoco><option timestep="0.001"/><worldbody>
  <body name="tumbler" pos="0 0 2" euler="10 20 30"><freejoint/>
    <geom type="box" size="0.3 0.2 0.1" contype="0" conaffinity="0"/>
    <site name="corner" pos="0.25 0.15 0.05" euler="0 45 0"/></body></worldbody>
<sensor><framelinacc objtype="site" objname="corner"/><frameangacc objtype="site" objname="corner"/>
  <framelinacc objtype="body" objname="tumbler"/><accelerometer site="corner"/></sensor></mujoco>"""


#: torchsim's steps from MuJoCo's resting pose until its readings settle: the soft contact model rests at MuJoCo's
#: depth, the impulse model at its own, which the box reaches ~100 steps on.
SETTLE = {"soft": 20, "impulse": 100}


def errors(sys, ours: np.ndarray, theirs: np.ndarray) -> dict:
    """``{sensor name: max abs error}``."""
    return {n: float(np.abs(ours[a:a + d] - theirs[a:a + d]).max())
            for n, a, d in zip(sys.sensor_names, sys.sensor_adr, sys.sensor_dims)}


def settled(xml: str, steps: int, contact_model: str):
    """MuJoCo's sensordata after ``steps`` steps from the model pose (read after ``mj_forward``), and torchsim's
    after ``SETTLE`` steps from MuJoCo's last ``qpos`` at rest (its own contacts and spring hinges take up the load)."""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    for _ in range(steps):
        mujoco.mj_step(m, d)
    mujoco.mj_forward(m, d)
    sys = torchsim.load_mjcf(xml, contact_model=contact_model, dtype=F64)
    state = torchsim.init(sys, torch.tensor(d.qpos)[None], torch.zeros(1, sys.nv, dtype=F64))
    ctrl = torch.zeros(1, sys.nu, dtype=F64)
    for _ in range(SETTLE[contact_model]):
        state = torchsim.step(sys, state, ctrl)
    return sys, torchsim.sensordata(sys, state, ctrl)[0].numpy(), d.sensordata.copy()


def mujoco_and_its_change(m: mujoco.MjModel, qpos, qvel):
    """MuJoCo's sensordata at ``qpos, qvel`` and how much each slot changes over one ``mj_step`` from there."""
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = qpos, qvel
    mujoco.mj_forward(m, d)
    start = d.sensordata.copy()
    mujoco.mj_step(m, d)
    mujoco.mj_forward(m, d)
    return start, np.abs(d.sensordata - start)


@pytest.mark.parametrize("contact_model", ["impulse", "soft"])
def test_resting_box(contact_model):
    """At rest the IMU reads +g upwards in its turned frame (framelinacc +g in the world's), the box no angular
    acceleration, the payload's weld its weight 4.905 N and that weight's moment about the mount, the box's free
    joint nothing (the floor's contact forces, 19.6 N, subtracted). MuJoCo settles for 1 s. The soft contact model
    rests at MuJoCo's depth: its box stays still (measured errors <= 5e-8), 1e-6 allows rounding. The impulse model
    rests at its own depth, which the box still approaches 100 steps on, by 2e-5 m/s per step: a mean acceleration
    of 0.01 m/s^2 (measured: 0.0096 m/s^2, 0.004 N on the payload's weld), 0.02 allows that. Both leave no room
    for a wrong frame, sign or missed contact force (>= 0.1 here)."""
    sys, ours, theirs = settled(BOX, 500, contact_model)
    err = errors(sys, ours, theirs)
    print(contact_model, err)
    assert max(err.values()) < {"soft": 1e-6, "impulse": 0.02}[contact_model]
    assert np.linalg.norm(theirs[0:3]) == pytest.approx(9.81) and theirs[5] == pytest.approx(9.81)
    assert np.linalg.norm(theirs[9:12]) == pytest.approx(0.5 * 9.81) and np.abs(theirs[12:15]).max() > 0.02


def test_hanging_pendulum_at_rest():
    """Hanging still, the bob's accelerometer reads +g, the pivot carries the whole weight (12.75 N) and the bob's
    site its own; no torques. torchsim's spring hinge first takes up the load (its State from ``init`` is unloaded),
    then holds the bob still: 50 steps on both are at rest and agree to 6e-12; 1e-6 leaves room for rounding and
    none for a wrong frame or sign."""
    m = mujoco.MjModel.from_xml_string(PENDULUM)
    sys = torchsim.load_mjcf(PENDULUM, dtype=F64)
    ctrl = torch.zeros(1, 0, dtype=F64)
    state = torchsim.init(sys, torch.zeros(1, 1, dtype=F64), torch.zeros(1, 1, dtype=F64))
    for _ in range(50):
        state = torchsim.step(sys, state, ctrl)
    assert abs(state.q.item()) < 1e-9 and abs(state.qd.item()) < 1e-9
    ours = torchsim.sensordata(sys, state, ctrl)[0].numpy()
    theirs, _ = mujoco_and_its_change(m, [0.0], [0.0])
    print(errors(sys, ours, theirs))
    assert max(errors(sys, ours, theirs).values()) < 1e-6
    assert np.linalg.norm(theirs[12:15]) == pytest.approx(1.3 * 9.81)


@pytest.mark.parametrize("q0, qd0", [(1.0, 0.0), (0.3, 2.0)])
def test_moving_pendulum(q0, qd0):
    """Released from 1 rad at rest, and swinging (0.3 rad, 2 rad/s): torchsim's reading 20 steps on (its spring
    hinge's take-up after ``init``, off by up to 11 m/s^2 in the first step, has died out by then to < 0.01) against
    MuJoCo's at the same ``qpos, qvel``. The mean over a step differs from the value at its start by about half the
    value's change over the step: each sensor within MuJoCo's own change of it over one step (measured: 0.25-0.66
    of it), plus 0.01 (m/s^2, N, N m; the values are 5-25) for the spring hinge's residual vibration (up to 3e-3
    measured at the pivot, whose acceleration and torque MuJoCo reads constant)."""
    m = mujoco.MjModel.from_xml_string(PENDULUM)
    sys = torchsim.load_mjcf(PENDULUM, dtype=F64)
    ctrl = torch.zeros(1, 0, dtype=F64)
    state = torchsim.init(sys, torch.tensor([[q0]], dtype=F64), torch.tensor([[qd0]], dtype=F64))
    for _ in range(20):
        state = torchsim.step(sys, state, ctrl)
    ours = torchsim.sensordata(sys, state, ctrl)[0].numpy()
    theirs, change = mujoco_and_its_change(m, state.q[0].numpy(), state.qd[0].numpy())
    err, allowed = errors(sys, ours, theirs), errors(sys, change, 0 * change)
    print({n: (round(err[n], 5), round(allowed[n], 5)) for n in err})
    assert all(err[n] <= allowed[n] + 0.01 for n in err), (err, allowed)
    assert np.abs(theirs).max() > 5.0  # the values are large against the tolerance


@pytest.mark.parametrize("contact_model", ["impulse", "soft"])
def test_lever_resting_on_the_floor(contact_model):
    """The hip's force and torque with the floor's push inside its subtree (about 4.9 N at the far end; the hinge
    carries the rest of the 1.4 kg), the tool's weld, the wrist's accelerometer. MuJoCo settles for 2 s, torchsim
    from its pose; the hinge's and the floor's shares then differ by 0.02-0.025 N between the engines (torchsim's
    spring hinge sags; they sum to the weight in both) and the torques by 0.013 N m (that sag's lever): 0.05 N,
    N m and m/s^2 (0.4 % of the weight, 0.5 % of g) leave room for that, none for a missed or doubled contact force
    (4.9 N)."""
    sys, ours, theirs = settled(LEVER, 1000, contact_model)
    err = errors(sys, ours, theirs)
    print(contact_model, err)
    assert max(err.values()) < 0.05
    assert np.linalg.norm(theirs[0:3]) > 4.0


def test_tumbling_body():
    """A falling box spinning about all three axes, read at its start (a free body's State from ``init`` is exact):
    the body's linear acceleration less gravity is 0, its site's is centripetal, its angular acceleration Euler's
    ``-I^-1 (w x I w)``. Each within MuJoCo's own change of it over one step (the step's mean against the value at
    its start), plus 1e-9."""
    m = mujoco.MjModel.from_xml_string(TUMBLER)
    sys = torchsim.load_mjcf(TUMBLER, dtype=F64)
    qvel = np.array([0.3, -0.2, 0.5, 3.0, -2.0, 4.0])
    state = torchsim.init(sys, torch.tensor(m.qpos0)[None], torch.tensor(qvel)[None])
    ours = torchsim.sensordata(sys, state, torch.zeros(1, 0, dtype=F64))[0].numpy()
    theirs, change = mujoco_and_its_change(m, m.qpos0, qvel)
    err, allowed = errors(sys, ours, theirs), errors(sys, change, 0 * change)
    print({n: (round(err[n], 5), round(allowed[n], 5)) for n in err})
    assert all(err[n] <= allowed[n] + 1e-9 for n in err), (err, allowed)
    assert np.abs(theirs[0:6]).max() > 5.0 and np.abs(theirs[6:9]).max() < 1e-9


def test_next_state_is_the_step_read():
    """Given the next State the sensors read it instead of stepping: the same values as stepping themselves, and
    a different next State reads differently (the State itself, which does not move: every acceleration 0, so the
    bob's framelinacc reads the acceleration less gravity, +9.81 m/s^2 up)."""
    sys = torchsim.load_mjcf(PENDULUM, dtype=F64)
    ctrl = torch.zeros(1, 0, dtype=F64)
    state = torchsim.init(sys, torch.tensor([[0.7]], dtype=F64), torch.zeros(1, 1, dtype=F64))
    stepped = torchsim.step(sys, state, ctrl)
    torch.testing.assert_close(torchsim.sensordata(sys, state, ctrl, next_state=stepped),
                               torchsim.sensordata(sys, state, ctrl), rtol=0, atol=0)
    still = torchsim.sensor(sys, state, "#1", ctrl, next_state=state)  # the bob's framelinacc, world frame
    torch.testing.assert_close(still, torch.tensor([[0.0, 0.0, 9.81]], dtype=F64))


def test_needs_the_controls():
    sys = torchsim.load_mjcf(PENDULUM, dtype=F64)
    state = torchsim.init(sys, torch.zeros(1, 1, dtype=F64), torch.zeros(1, 1, dtype=F64))
    with pytest.raises(ValueError, match="accelerometer sensors read the next step's accelerations.*pass ctrl"):
        torchsim.sensordata(sys, state)


REFUSED = {
    "connect": ("""<mujoco><worldbody><body name="a" pos="0 0 1"><freejoint/><geom size=".1"/><site name="s"/>
                 </body></worldbody><equality><connect body1="a" anchor="0 0 .1"/></equality>
                 <sensor><force site="s"/></sensor></mujoco>""", "connect or weld"),
    "static": ("""<mujoco><worldbody><body name="base" pos="0 0 1"><geom size=".1"/><site name="s"/>
                <body><joint axis="0 1 0"/><geom size=".1" pos=".2 0 0"/></body></body></worldbody>
                <sensor><torque site="s"/></sensor></mujoco>""", "fixed to the world"),
    "fused": ("""<mujoco><worldbody><geom type="plane" size="1 1 .1"/><body pos="0 0 1"><freejoint/><geom size=".1"/>
               <body pos=".2 0 0"><geom size=".1"/><site name="s"/></body></body></worldbody>
               <sensor><force site="s"/></sensor></mujoco>""", "both sides"),
}


@pytest.mark.parametrize("case", sorted(REFUSED))
def test_refused_where_external_forces_are_not_read(case):
    """Force and torque sensors whose subtree takes forces MuJoCo counts as external and torchsim does not read
    out (a connect constraint; a body fixed to the world; a welded child whose geoms collide, as its parent's do,
    through one fused torchsim body) are not computed: the warning names why and reading one raises."""
    xml, why = REFUSED[case]
    with pytest.warns(UserWarning, match=why):
        sys = torchsim.load_mjcf(xml, dtype=F64)
    state = torchsim.init(sys, sys.q0[None].clone(), torch.zeros(1, sys.nv, dtype=F64))
    with pytest.raises(torchsim.UnsupportedMJCFError, match=why):
        torchsim.sensor(sys, state, "#0", torch.zeros(1, 0, dtype=F64))


def test_contact_forces_of_other_methods_are_refused():
    """Force sensors of a model with contacts read the spring method's contact forces; another method is named."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sys = torchsim.load_mjcf(BOX, method="xpbd", dtype=F64)
    state = torchsim.init(sys, sys.q0[None].clone(), torch.zeros(1, sys.nv, dtype=F64))
    with pytest.raises(NotImplementedError, match="spring method only, not 'xpbd'"):
        torchsim.sensor(sys, state, "mount_force", torch.zeros(1, 0, dtype=F64))
    assert torchsim.sensor(sys, state, "imu_acc", torch.zeros(1, 0, dtype=F64)).shape == (1, 3)
