"""Hinge angles are continuous through full turns, as MuJoCo's ``qpos``: a pendulum and a
cart-pole spun over the top several times, against MuJoCo on the same MJCF, float64."""

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from models import F64, METHODS, PENDULUM

# the pole's qpos0 is ref = 0.5 rad: MuJoCo's angle counts from there, and so must ours
CART_POLE = """
<mujoco><option timestep="0.001"/><worldbody>
  <body pos="0 0 1"><joint type="slide" axis="1 0 0"/><geom type="box" size="0.2 0.1 0.05" mass="1"/>
    <body><joint type="hinge" axis="0 1 0" ref="0.5"/><geom type="capsule" fromto="0 0 0 0 0 0.6" size="0.03"/>
    </body></body></worldbody></mujoco>"""


def _mujoco_angles(xml: str, qvel: list, steps: int) -> np.ndarray:
    """The hinge's qpos (last coordinate) after each of ``steps`` timesteps of MuJoCo."""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    d.qvel[:] = qvel
    angles = []
    for _ in range(steps):
        mujoco.mj_step(m, d)
        angles.append(d.qpos[-1])
    return np.array(angles)


# the wrap was in reading angles back, common to both methods: the cart-pole (the slower scene) runs one
@pytest.mark.parametrize("method, xml, qvel", [(method, PENDULUM, [30.0]) for method in METHODS]
                         + [("spring", CART_POLE, [0.0, 36.0])], ids=[f"pendulum-{m}" for m in METHODS] + ["cart_pole"])
def test_hinge_angle_runs_on_through_full_turns_like_mujoco(method, xml, qvel):
    steps = 500  # 0.5 s: the hinge makes ~2.3 turns
    sys = torchsim.load_mjcf(xml, method=method, dtype=F64)
    state = torchsim.init(sys, torch.as_tensor(sys.q0, dtype=F64)[None], torch.tensor([qvel], dtype=F64))
    ctrl = torch.zeros(1, sys.nu, dtype=F64)
    angles = []
    for _ in range(steps):
        state = torchsim.step(sys, state, ctrl)
        angles.append(state.q[0, -1].item())
    angles = np.array(angles)
    reference = _mujoco_angles(xml, qvel, steps)
    assert reference[-1] - reference[0] > 4 * np.pi  # the scene does what the test is about
    # continuous: no step moves the angle by more than its speed allows (a wrap would jump by 2 pi)
    assert np.abs(np.diff(angles)).max() < 0.05
    # and it is MuJoCo's angle, not one off by whole turns. The spring method's own error is ~0.05% of the
    # travel (8e-3 rad after 2.6 turns at 18 rad/s; MuJoCo dt vs dt/4: 2e-4). XPBD's projection of the hinge
    # removes energy growing with speed (7.5% of the travel at 30 rad/s, 4% at 18). Both are far below a wrap's 2 pi
    tolerance = (0.01 if method == "spring" else 0.1) * np.abs(reference).max()
    assert np.abs(angles - reference).max() < tolerance


def test_init_keeps_hinge_angles_beyond_a_turn():
    sys = torchsim.load_mjcf(CART_POLE, dtype=F64)
    q = torch.tensor([[0.3, 7.0], [-0.2, -9.5]], dtype=F64)
    state = torchsim.init(sys, q, torch.zeros(2, sys.nv, dtype=F64))
    torch.testing.assert_close(state.q, q)
    after = torchsim.step(sys, state, torch.zeros(2, sys.nu, dtype=F64))
    assert (after.q[:, 1] - q[:, 1]).abs().max() < 0.01  # one step from rest moves it little, and not by a turn


# dm_control's finger: a range of [-110, 110] degrees about ref -90 reaches past half a turn from ref, where body
# poses alone would read the angle 2 pi lower. Driven up into its upper limit, the link must stop there as in
# MuJoCo (read in (ref - pi, ref + pi], the sweep past 90 degrees looked like a lower-limit violation of ~5 rad, and
# the env diverged)
WIDE_RANGE = """
<mujoco><option timestep="0.002"/><compiler angle="degree"/><worldbody>
  <body pos="0 0 1"><joint name="hinge" type="hinge" axis="0 1 0" ref="-90" range="-110 110" damping="0.05"/>
    <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.02"/>
  </body></worldbody><actuator><motor joint="hinge"/></actuator></mujoco>"""


@pytest.mark.parametrize("method", METHODS)
def test_range_past_half_a_turn_from_ref_is_enforced_like_mujoco(method):
    m = mujoco.MjModel.from_xml_string(WIDE_RANGE)
    d = mujoco.MjData(m)
    d.ctrl[:] = 1.0
    sys = torchsim.load_mjcf(WIDE_RANGE, method=method, dtype=F64)
    state = torchsim.init(sys, torch.as_tensor(m.qpos0, dtype=F64)[None], torch.zeros(1, 1, dtype=F64))
    ctrl = torch.ones(1, 1, dtype=F64)
    angles, reference = [], []
    for _ in range(600):
        mujoco.mj_step(m, d)
        state = torchsim.step(sys, state, ctrl)
        angles.append(state.q[0, 0].item())
        reference.append(d.qpos[0])
    upper = m.jnt_range[0, 1]
    assert not state.diverged.any()
    # MuJoCo's soft limit lets the link overshoot it by 5 degrees (0.088 rad at 2 ms, 0.095 at 0.1 ms); ours is the
    # same soft limit (tests/test_soft_limits.py): 0.092 rad at 0.5 ms substeps, both methods
    overshoot, mj_overshoot = max(angles) - upper, max(reference) - upper
    assert mj_overshoot > 0.05 and abs(overshoot - mj_overshoot) < 0.1 * mj_overshoot
    assert abs(angles[-1] - reference[-1]) < 1e-4  # both come to rest 0.76 mrad past the limit (to 7e-6 rad)


# An unlimited hinge with a spring (springref 0), started at rest 4 rad round: MuJoCo's spring turns it back through
# 0. A substep that read the angle within half a turn of ref saw 4 - 2 pi and drove it on to 2 pi instead.
SPRUNG = """
<mujoco><option timestep="0.002" gravity="0 0 0"/><worldbody>
  <body><joint name="hinge" type="hinge" axis="0 0 1" stiffness="0.5" damping="0.05"/>
    <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.02"/>
  </body></worldbody></mujoco>"""


@pytest.mark.parametrize("method", METHODS)
def test_spring_on_unlimited_hinge_sees_angle_past_half_a_turn_like_mujoco(method):
    m = mujoco.MjModel.from_xml_string(SPRUNG)
    d = mujoco.MjData(m)
    d.qpos[0] = 4.0
    sys = torchsim.load_mjcf(SPRUNG, method=method, dtype=F64)
    state = torchsim.init(sys, torch.tensor([[4.0]], dtype=F64), torch.zeros(1, 1, dtype=F64))
    ctrl = torch.zeros(1, 0, dtype=F64)
    for _ in range(250):
        mujoco.mj_step(m, d)
        state = torchsim.step(sys, state, ctrl)
    assert d.qpos[0] < 3.0  # the scene does what the test is about: the spring pulls it back past pi
    assert abs(state.q[0, 0].item() - d.qpos[0]) < 0.02 * (4.0 - d.qpos[0])
