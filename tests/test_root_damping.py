"""Damping, armature and stiffness on free and ball joints (``joint_space.root_rate_solve``) against closed forms
and MuJoCo.

MuJoCo's Euler step takes damping implicitly at its 1 ms timestep; torchsim too, at its 0.5 ms substeps. For a
decay rate ``lambda`` both err from ``exp(-lambda t)`` by about ``t lambda h / 2`` relative (1e-3 and 2e-3 here):
closed forms are checked to 0.5 % and MuJoCo's trajectories to 1 %.
"""

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from models import F64, METHODS

FREE = """
<mujoco><option gravity="0 0 0" timestep="{dt}"/><worldbody>
  <body pos="0 0 1"><joint type="free" damping="{damping}" armature="{armature}" stiffness="{stiffness}"/>
    <geom type="box" size="0.1 0.2 0.3" pos="{com}" mass="2" contype="0" conaffinity="0"/></body>
</worldbody></mujoco>"""
BALL = """
<mujoco><option gravity="0 0 0" timestep="0.001"/><worldbody>
  <body pos="0 0 1"><joint type="ball" damping="{damping}" armature="{armature}" stiffness="{stiffness}"/>
    <geom type="box" size="0.1 0.2 0.3" mass="2" contype="0" conaffinity="0"/></body>
</worldbody></mujoco>"""
MASS, I_ZZ, I_XX = 2.0, 2.0 / 3 * (0.1**2 + 0.2**2), 2.0 / 3 * (0.2**2 + 0.3**2)  # the box's, about its centre


# each method, and the spring method's articulated model (the tree's solve: torchsim.tree_solve)
SOLVES = [(method, "impulse") for method in METHODS] + [("spring", "articulated")]


def _rollout(xml, qpos, qvel, seconds, method, contact_model="impulse"):
    """MuJoCo's and torchsim's (float64, eager) ``qpos, qvel`` at every step: 2 arrays each ``(T, nq | nv)``."""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = qpos, qvel
    sys = torchsim.load_mjcf(xml, method=method, dtype=F64, contact_model=contact_model)
    state = torchsim.init(sys, torch.as_tensor(d.qpos[None].copy()), torch.as_tensor(d.qvel[None].copy()))
    ctrl = torch.zeros(1, 0, dtype=F64)
    mj, ours = [], []
    for _ in range(round(seconds / m.opt.timestep)):
        mujoco.mj_step(m, d)
        state = torchsim.step(sys, state, ctrl)
        mj.append(np.concatenate((d.qpos, d.qvel)))
        ours.append(torch.cat((state.q[0], state.qd[0])).numpy())
    return np.array(mj), np.array(ours)


@pytest.mark.parametrize("method, contact_model", SOLVES)
def test_free_body_damping_decays_exponentially(method, contact_model):
    """Sliding at (1, 0.5, 0) m/s and spinning at 3 rad/s about its z axis, damping 0.5 and armature 0.1 on every
    dof: the speeds decay as ``exp(-d t / (m + J))`` and ``exp(-d t / (I_zz + J))`` (armature adds to every dof's
    inertia), over 1 s, and as MuJoCo's."""
    xml = FREE.format(dt=0.001, damping=0.5, armature=0.1, stiffness=0, com="0 0 0")
    mj, ours = _rollout(xml, [0, 0, 1, 1, 0, 0, 0], [1, 0.5, 0, 0, 0, 3], 1.0, method, contact_model)
    t = 1.0
    lin, ang = np.exp(-0.5 * t / (MASS + 0.1)), np.exp(-0.5 * t / (I_ZZ + 0.1))
    # MuJoCo's implicit damping at 1 ms leaves the spin 0.7 % above the exponential (the articulated model, one
    # substep per timestep, does the same)
    assert np.allclose(ours[-1, 7:], [lin, 0.5 * lin, 0, 0, 0, 3 * ang], rtol=1e-2, atol=1e-9)
    assert np.allclose(ours[:, 7:], mj[:, 7:], rtol=1e-2, atol=1e-9)
    assert np.abs(ours[:, :3] - mj[:, :3]).max() < 1e-3  # positions: the integral of the same decay


@pytest.mark.parametrize("method", METHODS)
def test_free_body_damping_off_its_centre(method):
    """MuJoCo damps the velocity of the body frame's origin, here 11 cm from the COM: the spin then drags the
    body sideways. With MuJoCo at a 0.2 ms step (its own discretisation error below the bound), paths within 0.3 mm
    over 0.5 s."""
    xml = FREE.format(dt=0.0002, damping=0.5, armature=0, stiffness=0, com="0.1 0.05 0")
    mj, ours = _rollout(xml, [0, 0, 1, 1, 0, 0, 0], [1, 0.5, 0, 0, 0, 3], 0.5, method)
    assert np.abs(ours[:, :7] - mj[:, :7]).max() < 3e-4
    assert np.abs(ours[:, 7:] - mj[:, 7:]).max() < 1e-3


@pytest.mark.parametrize("method, contact_model", SOLVES)
def test_ball_joint_oscillates_with_armature_and_stiffness(method, contact_model):
    """Turned 0.3 rad about x and released: a torsion pendulum of stiffness 2 N m/rad on ``I_xx + J`` (armature
    0.05), damping 0.02. Period ``2 pi sqrt((I_xx + J) / k)`` (1.642 s) from the rotation's zero crossings, as
    MuJoCo's to 0.5 %, and the path (quaternions) within 5e-4 of MuJoCo's over 1.7 s; its amplitude after one
    period within 1 % of MuJoCo's."""
    xml = BALL.format(damping=0.02, armature=0.05, stiffness=2.0)
    mj, ours = _rollout(xml, [np.cos(0.15), np.sin(0.15), 0, 0], [0, 0, 0], 1.7, method, contact_model)
    assert np.abs(ours[:, :4] - mj[:, :4]).max() < 5e-4

    def period(x):
        crossings = np.flatnonzero(np.diff(np.sign(x[:, 1])) != 0)
        exact = [c + x[c, 1] / (x[c, 1] - x[c + 1, 1]) for c in crossings[:2]]  # interpolated [steps]
        return 2 * (exact[1] - exact[0]) * 1e-3

    expected = 2 * np.pi * np.sqrt((I_XX + 0.05) / 2.0)
    assert abs(period(mj) / expected - 1) < 5e-3
    assert abs(period(ours) / period(mj) - 1) < 5e-3
    one_period = round(expected / 1e-3)
    assert abs(ours[one_period, 1] / mj[one_period, 1] - 1) < 1e-2
    assert ours[one_period, 1] < 0.99 * np.sin(0.15)  # damped


def test_free_body_refusals_name_the_body():
    """Stiffness on a free joint, and armature on one whose origin is off the COM, are refused by name."""
    with pytest.raises(torchsim.UnsupportedMJCFError, match="stiffness on the free joint of body"):
        torchsim.load_mjcf(FREE.format(dt=0.001, damping=0, armature=0, stiffness=1, com="0 0 0"))
    with pytest.raises(torchsim.UnsupportedMJCFError, match="armature on the free joint of body .* off its centre"):
        torchsim.load_mjcf(FREE.format(dt=0.001, damping=0, armature=0.1, stiffness=0, com="0.1 0 0"))
    assert torchsim.load_mjcf(FREE.format(dt=0.001, damping=0.1, armature=0.1, stiffness=0, com="0 0 0")).root_passive


def test_kernel_runs_root_damping():
    """The generated C++ step (``kernel`` strategy) on free bodies with damping and armature (one with its origin
    off its COM) and a ball joint with all three: the same states as the reference step, by test_strategies'
    bound."""
    from test_strategies import _check_against_reference

    xml = """<mujoco><option timestep="0.002"/><worldbody>
      <body pos="0 0 1"><joint type="free" damping="0.5" armature="0.1"/>
        <geom type="box" size="0.1 0.2 0.3" contype="0" conaffinity="0"/>
        <body pos="0 0 -0.4"><joint type="ball" damping="0.02" armature="0.05" stiffness="2"/>
          <geom type="sphere" size="0.1" pos="0 0 -0.1" contype="0" conaffinity="0"/></body></body>
      <body pos="1 0 1"><joint type="free" damping="0.3"/>
        <geom type="box" size="0.1 0.2 0.3" pos="0.1 0 0" contype="0" conaffinity="0"/></body>
    </worldbody></mujoco>"""
    sys = torchsim.load_mjcf(xml, dtype=F64)
    stepper = torchsim.Stepper(sys, "kernel", threads=1)
    start = torchsim.init(sys, sys.q0[None].clone(), 0.5 * torch.ones(1, sys.nv, dtype=F64))
    _check_against_reference("root damping kernel", sys, stepper, start, torch.zeros(10, 1, 0, dtype=F64), 1, 1e-3)
    assert stepper.strategy == "kernel"  # no fallback
