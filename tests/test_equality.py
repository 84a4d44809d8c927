"""Equality constraints (``<equality><tendon>`` and ``<joint>``) against MuJoCo 4.0: the constraint's residual, rate,
Jacobian, gains, impedance and inverse inertia; two pendulums held together by a tendon; ``polycoef``; ``active``;
``<weld>``/``<connect>`` kept apart (``torchsim.welds``)."""

import mujoco
import numpy as np
import torch

import torchsim
from torchsim import equality
from torchsim.actuators import dof_forces
from models import F64

# Two separate pendulums (hinges h1, h2: a 0.4 m horizontal rod and a 0.2 m hanging one), a vertical slide s, a
# motor on h2 and the fixed tendon ``pair = h1 - h2``; {eq} fills <equality>.
PENDULUMS = """
<mujoco>
  <option timestep="{dt}" gravity="0 0 -9.81" jacobian="dense"/>
  <worldbody>
    <body pos="0 0 1"><joint name="h1" type="hinge" axis="0 1 0"/>
      <geom type="capsule" size=".05" fromto="0 0 0 .4 0 0" contype="0" conaffinity="0"/></body>
    <body pos="1 0 1"><joint name="h2" type="hinge" axis="0 1 0"/>
      <geom type="capsule" size=".03" fromto="0 0 0 0 0 -.2" contype="0" conaffinity="0"/></body>
    <body pos="2 0 1"><joint name="s" type="slide" axis="0 0 1"/>
      <geom type="box" size=".1 .1 .1" contype="0" conaffinity="0"/></body>
    <body pos="3 0 1"><joint name="ball" type="ball"/>
      <geom type="sphere" size=".1" contype="0" conaffinity="0"/></body>
  </worldbody>
  <tendon>
    <fixed name="pair"><joint joint="h1" coef="1"/><joint joint="h2" coef="-1"/></fixed>
    <fixed name="mixed"><joint joint="h2" coef="0.5"/><joint joint="s" coef="2"/></fixed>
  </tendon>
  <equality>{eq}</equality>
  <actuator><motor joint="h2" gear="1"/></actuator>
</mujoco>
"""
HOLD = '<tendon name="hold" tendon1="pair" {extra}/>'
STEP = 0.004  # torchsim substeps it 4 times; MuJoCo's reference takes 4 steps of a quarter of it
CTRL = 0.5  # [N m] on h2


def model(eq: str, dt: float = STEP) -> str:
    return PENDULUMS.format(dt=dt, eq=eq)


def q0(h1: float, h2: float) -> np.ndarray:
    return np.array([h1, h2, 0.0, 1.0, 0.0, 0.0, 0.0])


def mujoco_rollout(xml: str, seconds: float, start: np.ndarray, substeps: int = 1) -> np.ndarray:
    """MuJoCo's ``qpos`` of the hinges after each ``STEP``."""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    d.qpos[:], d.ctrl[:] = start, CTRL
    out = []
    for _ in range(round(seconds / STEP)):
        for _ in range(substeps):
            mujoco.mj_step(m, d)
        out.append(d.qpos[:2].copy())
    return np.array(out)


def torchsim_rollout(xml: str, seconds: float, start: np.ndarray) -> np.ndarray:
    sys = torchsim.load_mjcf(xml, dtype=F64, substeps=4)
    state = torchsim.init(sys, torch.as_tensor(start)[None], torch.zeros(1, sys.nv, dtype=F64))
    ctrl = torch.full((1, sys.nu), CTRL, dtype=F64)
    out = []
    for _ in range(round(seconds / sys.timestep)):
        state = torchsim.step(sys, state, ctrl)
        out.append(state.q[0, :2].numpy().copy())
    return np.array(out)


def test_constraint_terms_match_mujoco():
    """Tendon and joint constraints, with and without a second side, polynomial ``polycoef``, direct and default
    ``solref``: residual, rate, gains, impedance and inverse inertia equal MuJoCo's ``efc_pos``, ``efc_vel``,
    ``efc_KBIP``, ``efc_diagA`` (the approximate inverse inertia, at ``qpos0``), ``efc_aref``, and the generalized
    force is ``efc_J^T`` times the explicit soft force."""
    eq = """<tendon tendon1="pair" tendon2="mixed" polycoef="0.05 0.5 0.3 -0.2 0.1" solref="0.01 0.7"/>
      <tendon tendon1="mixed" polycoef="0.1 0 0 0 0" solref="-500 -20" solimp="0.8 0.9 0.2 0.3 3"/>
      <joint joint1="h1" joint2="s" polycoef="-0.1 2 0 0.5 0"/>
      <joint joint1="s" polycoef="0.02 0 0 0 0"/>"""
    xml = model(eq)
    m, sys = mujoco.MjModel.from_xml_string(xml), torchsim.load_mjcf(xml, dtype=F64)
    d = mujoco.MjData(m)
    rng = np.random.default_rng(0)
    for _ in range(5):
        d.qpos[:] = q0(*rng.uniform(-1, 1, 2))
        d.qpos[2] = rng.uniform(-0.3, 0.3)
        d.qvel[:] = rng.normal(size=m.nv)
        mujoco.mj_forward(m, d)
        rows = np.flatnonzero(d.efc_type == int(mujoco.mjtConstraint.mjCNSTR_EQUALITY))
        assert len(rows) == 4
        q = torch.as_tensor(d.qpos.copy())[sys.dof_qpos][:, None]
        qd = torch.as_tensor(d.qvel.copy())[sys.dof_qvel][:, None]
        r, v, _ = equality.residuals(sys, q, qd)
        np.testing.assert_allclose(r[:, 0].numpy(), d.efc_pos[rows], atol=1e-12)
        np.testing.assert_allclose(v[:, 0].numpy(), d.efc_vel[rows], atol=1e-12)
        k, b, imp = d.efc_KBIP[rows, 0], d.efc_KBIP[rows, 1], d.efc_KBIP[rows, 2]
        np.testing.assert_allclose(sys.eq_gains.numpy(), np.stack([k, b], -1), rtol=1e-12)
        np.testing.assert_allclose(sys.eq_invweight.numpy(), d.efc_diagA[rows], rtol=1e-12)
        np.testing.assert_allclose(-b * d.efc_vel[rows] - k * imp * d.efc_pos[rows], d.efc_aref[rows], rtol=1e-12)
        force = imp / d.efc_diagA[rows] * d.efc_aref[rows]
        expected = (d.efc_J.reshape(d.nefc, m.nv)[rows].T @ force)[sys.dof_qvel]
        zero = torch.zeros_like(q)
        np.testing.assert_allclose(equality.add_forces(sys, zero, q, qd)[:, 0].numpy(), expected, rtol=1e-10,
                                   atol=1e-10)
        # and dof_forces adds them (the motor's ctrl is 0, no springs)
        tau = dof_forces(sys, q, qd, torch.zeros(1, 1, dtype=F64))
        np.testing.assert_allclose(tau[:, 0].numpy(), expected, rtol=1e-10, atol=1e-10)


def test_tendon_equality_holds_two_pendulums_like_mujoco():
    """A horizontal rod and a hanging one, driven by a motor and gravity, held at ``h1 - h2 = 0`` for 0.3 s (free,
    they drift 0.40 rad apart). Measured, MuJoCo holds the residual within 0.63 mrad (at 4 ms and 1 ms alike),
    torchsim within 9.2 mrad, 15 times as far: its explicit force leaves out MuJoCo's ``a0`` term, so under a steady
    load the residual is ``1 / (1 - imp)`` = 20 times MuJoCo's (``torchsim.equality``; default ``solimp``, ``imp =
    0.95``). The motion is within MuJoCo's own time-discretization error (its 4 ms step against 1 ms, 10 mrad):
    measured, the mean angle 4.0 mrad off MuJoCo's, h1 0.3 mrad and h2 8.3 mrad."""
    start, seconds = q0(0.3, 0.3), 0.3
    xml = model(HOLD.format(extra=""))
    coarse = mujoco_rollout(xml, seconds, start)
    fine = mujoco_rollout(model(HOLD.format(extra=""), STEP / 4), seconds, start, substeps=4)
    free = mujoco_rollout(model(""), seconds, start)
    ours = torchsim_rollout(xml, seconds, start)

    def residual(q):
        return np.abs(q[:, 0] - q[:, 1]).max()

    def mean(q):
        return q.mean(1)

    ours_residual, mujoco_residual = residual(ours), residual(fine)
    assert residual(free) > 0.3
    assert 10 * mujoco_residual < ours_residual < 25 * mujoco_residual, (ours_residual, mujoco_residual)
    assert ours_residual < 0.01, ours_residual
    mujoco_own = np.abs(mean(coarse) - mean(fine)).max()
    assert np.abs(mean(free) - mean(fine)).max() > 10 * mujoco_own  # the constraint matters at this tolerance
    assert np.abs(mean(ours) - mean(fine)).max() < mujoco_own, (np.abs(mean(ours) - mean(fine)).max(), mujoco_own)
    hinge_own = np.abs(coarse - fine).max(0)
    assert np.all(np.abs(ours - fine).max(0) < hinge_own), (np.abs(ours - fine).max(0), hinge_own)


def test_polycoef_offset_is_held():
    """``polycoef="0.1 ..."`` holds ``h1 - h2`` at 0.1 rad, as MuJoCo does (started there; without the offset the
    constraint pulls the pair back to 0)."""
    start, seconds = q0(0.4, 0.3), 0.2
    xml = model(HOLD.format(extra='polycoef="0.1 1 0 0 0"'))
    ours = torchsim_rollout(xml, seconds, start)
    reference = mujoco_rollout(model(HOLD.format(extra='polycoef="0.1 1 0 0 0"'), STEP / 4), seconds, start, 4)
    ours_offset, mujoco_offset = ours[:, 0] - ours[:, 1], reference[:, 0] - reference[:, 1]
    assert np.abs(mujoco_offset - 0.1).max() < 1e-3
    assert np.abs(ours_offset - 0.1).max() < 0.01, np.abs(ours_offset - 0.1).max()
    unshifted = torchsim_rollout(model(HOLD.format(extra="")), 0.1, start)
    assert np.abs(unshifted[-5:, 0] - unshifted[-5:, 1]).max() < 0.02  # pulled back to 0


def test_inactive_constraint_does_nothing():
    inactive = model(HOLD.format(extra='active="false"'))
    sys = torchsim.load_mjcf(inactive, dtype=F64)
    assert not sys.eq_constraints and sys.eq_ref.shape[0] == 0
    assert torchsim.load_mjcf(model(HOLD.format(extra="")), dtype=F64).eq_constraints
    start = q0(0.3, 0.3)
    np.testing.assert_array_equal(torchsim_rollout(inactive, 0.04, start), torchsim_rollout(model(""), 0.04, start))
    np.testing.assert_allclose(mujoco_rollout(inactive, 0.04, start), mujoco_rollout(model(""), 0.04, start))


def test_weld_and_connect_are_body_constraints():
    """``<connect>`` and ``<weld>`` load as body constraints (``torchsim.welds``, tests/test_mocap_weld.py), not as
    dof equalities; an inactive one is dropped."""
    eq = '<connect body1="b" anchor="0 0 0"/><weld body1="b" active="false"/>'
    sys = torchsim.load_mjcf(model(eq).replace('<body pos="2 0 1">', '<body name="b" pos="2 0 1">'))
    assert not sys.eq_constraints and sys.weld_frame.shape == (1, 2) and sys.welds
