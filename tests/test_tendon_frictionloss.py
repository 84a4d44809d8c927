"""Fixed-tendon ``frictionloss``: dry friction along a tendon's coordinate ``L = c_a q_a + c_b q_b``, against the exact
Coulomb solution and against MuJoCo.

Two hinges coupled by one tendon (``c_a = 0.5``, ``c_b = -1``), no other coupling. The friction is an impulse along
the tendon of at most ``h frictionloss`` per substep (``torchsim.joint_space``), entering each dof as ``c_k`` times
itself, so it decelerates the tendon's rate at ``frictionloss (c_a^2 / I_a + c_b^2 / I_b)`` and holds it at 0 once
stopped. MuJoCo's friction is a soft constraint (it creeps and lags a little), so the exact solution is the
reference where there is one, and MuJoCo at a 4x finer timestep where there is none.
"""

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from models import F64, cached_third_party
from torchsim.execution.kernel import emit_cuda
from torchsim.execution.kernel.step import StepKernel
from torchsim.io_mjcf import UnsupportedMJCFError

MJ_DT = 0.002
STEP = 0.01  # our step and the sampling interval [s]
COEF_A, COEF_B = 0.5, -1.0


def spinning_pair(frictionloss):
    """Two bodies spinning about vertical hinges through their COMs: no gravity torque, no centripetal pull."""
    return f"""<mujoco><option timestep="{MJ_DT}"/><worldbody>
      <body pos="0 0 1"><joint name="a" type="hinge" axis="0 0 1"/>
        <geom type="box" size="0.3 0.05 0.05" mass="1" contype="0" conaffinity="0"/></body>
      <body pos="1 0 1"><joint name="b" type="hinge" axis="0 0 1"/>
        <geom type="box" size="0.2 0.2 0.05" mass="2" contype="0" conaffinity="0"/></body>
      </worldbody><tendon><fixed name="t" frictionloss="{frictionloss}">
        <joint joint="a" coef="{COEF_A}"/><joint joint="b" coef="{COEF_B}"/></fixed></tendon></mujoco>"""


def pendulum_and_wheel(frictionloss):
    """Hinge ``a``: the 0.5 m pendulum of ``test_frictionloss`` (gravity torque 7.36 N m horizontal, inertia 0.344
    kg m^2); hinge ``b``: a wheel about a vertical axis (0.053 kg m^2). Held, the tendon needs 0.55 N at the start."""
    return f"""<mujoco><option timestep="{MJ_DT}"/><worldbody>
      <body pos="0 0 1"><joint name="a" type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0.5 0 0" size="0.05" mass="1" contype="0" conaffinity="0"/>
        <geom type="sphere" pos="0.5 0 0" size="0.1" mass="1" contype="0" conaffinity="0"/></body>
      <body pos="1 0 1"><joint name="b" type="hinge" axis="0 0 1"/>
        <geom type="box" size="0.2 0.2 0.05" mass="2" contype="0" conaffinity="0"/></body>
      </worldbody><tendon><fixed name="t" frictionloss="{frictionloss}">
        <joint joint="a" coef="{COEF_A}"/><joint joint="b" coef="{COEF_B}"/></fixed></tendon></mujoco>"""


def mujoco_run(xml, qd0, duration, dt=MJ_DT):
    """MuJoCo's coordinates and rates ``(n, 2)`` every ``STEP`` seconds, from 0 with rates ``qd0``."""
    m = mujoco.MjModel.from_xml_string(xml)
    m.opt.timestep = dt
    d = mujoco.MjData(m)
    d.qvel[:] = qd0
    q, qd = [], []
    per_sample = int(round(STEP / dt))
    for i in range(int(round(duration / dt))):
        mujoco.mj_step(m, d)
        if (i + 1) % per_sample == 0:
            q.append(d.qpos.copy())
            qd.append(d.qvel.copy())
    return np.array(q), np.array(qd)


def torchsim_run(xml, qd0, duration, method, substeps):
    sys = torchsim.load_mjcf(xml.replace(f'timestep="{MJ_DT}"', f'timestep="{STEP}"'), method=method, dtype=F64,
                             substeps=substeps)
    state = torchsim.init(sys, torch.zeros(1, 2, dtype=F64), torch.tensor([qd0], dtype=F64))
    ctrl = torch.zeros(1, 0, dtype=F64)
    q, qd = [], []
    for _ in range(int(round(duration / STEP))):
        state = torchsim.step(sys, state, ctrl)
        q.append(state.q[0].numpy().copy())
        qd.append(state.qd[0].numpy().copy())
    assert not state.diverged.any()
    return np.array(q), np.array(qd)


def hinge_inertias(xml):
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    full = np.zeros((2, 2))
    mujoco.mj_fullM(m, d, full)
    return full[0, 0], full[1, 1]


@pytest.mark.parametrize("method, substeps", [("spring", 10), ("xpbd", 10)])
def test_sliding_tendon_stops_as_exact_coulomb_friction(method, substeps):
    """Hinge ``a`` spins at 3 rad/s, ``b`` at rest, frictionloss 0.2 N: the tendon's rate 1.5 falls at
    ``0.2 (c_a^2 / I_a + c_b^2 / I_b) = 5.37 /s`` to 0 at 0.279 s, each dof's rate changing at ``-c_k 0.2 / I_k``,
    then both turn on together. Our impulse is exact Coulomb friction in the substep it acts (1e-6 rad/s allows
    rounding only); MuJoCo's soft friction reaches the same end rates, 0.012 rad/s off while the tendon stops."""
    xml = spinning_pair(0.2)
    inertia_a, inertia_b = hinge_inertias(xml)
    t = STEP * np.arange(1, 51)
    stop = (COEF_A * 3.0) / (0.2 * (COEF_A**2 / inertia_a + COEF_B**2 / inertia_b))
    sliding = np.minimum(t, stop)[:, None]
    exact = np.array([3.0, 0.0]) - np.array([COEF_A / inertia_a, COEF_B / inertia_b]) * 0.2 * sliding
    _, ours = torchsim_run(xml, [3.0, 0.0], 0.5, method, substeps)
    _, mj = mujoco_run(xml, [3.0, 0.0], 0.5)
    print(f"{method}: max |qd - exact| torchsim {abs(ours - exact).max():.2e}, MuJoCo {abs(mj - exact).max():.2e}")
    np.testing.assert_allclose(ours, exact, atol=1e-6)
    np.testing.assert_allclose(ours[-1], mj[-1], atol=1e-6)  # the same end rates: the tendon held in both


@pytest.mark.parametrize("method, substeps", [("spring", 10), ("xpbd", 20)])
@pytest.mark.parametrize("frictionloss", [2.0, 0.3])
def test_gravity_against_tendon_friction_tracks_mujoco(method, substeps, frictionloss):
    """The pendulum falls from horizontal against the tendon's friction, dragging the wheel. 2 N > 0.55 N holds the
    tendon: the two turn as one (``q_b = q_a / 2``) with inertia ``I_a + I_b c_a^2 / c_b^2``; 0.3 N lets it slip,
    the wheel lagging (0.70 rad after 0.5 s, 1.07 held, 0 without friction). Over 0.5 s, our coordinates stay
    within twice MuJoCo's own timestep sensitivity (MuJoCo at 2 ms against 0.5 ms: 0.005 rad) of MuJoCo at 0.5 ms."""
    xml = pendulum_and_wheel(frictionloss)
    coarse, _ = mujoco_run(xml, [0.0, 0.0], 0.5)
    fine, _ = mujoco_run(xml, [0.0, 0.0], 0.5, dt=MJ_DT / 4)
    ours, _ = torchsim_run(xml, [0.0, 0.0], 0.5, method, substeps)
    sensitivity = abs(coarse - fine).max()
    print(f"{method}, frictionloss {frictionloss}: max |q - MuJoCo dt/4| {abs(ours - fine).max():.4f} rad, MuJoCo's "
          f"dt sensitivity {sensitivity:.4f} rad")
    assert abs(ours - fine).max() < 2 * sensitivity
    if frictionloss == 2.0:  # held: L = c_a q_a + c_b q_b stays 0 up to a creep, MuJoCo's soft one 0.003 rad
        creep, mj_creep = (abs(q @ np.array([COEF_A, COEF_B])).max() for q in (ours, fine))
        print(f"tendon creep over 0.5 s: torchsim {creep:.2e}, MuJoCo dt/4 {mj_creep:.2e}")
        assert creep <= {"spring": 1e-6, "xpbd": mj_creep}[method]  # XPBD's projection creeps (test_frictionloss)


def test_structure_decided_at_load():
    """Which tendons have friction is static: a model without carries none, and its step does no friction work."""
    assert torchsim.load_mjcf(spinning_pair(0.0)).ten_friction.numel() == 0
    sys = torchsim.load_mjcf(spinning_pair(0.2))
    assert sys.ten_friction.tolist() == [0] and sys.ten_friction_dof.tolist() == [0, 1]
    assert sys.ten_friction_coef.tolist() == [COEF_A, COEF_B] and sys.dof_friction_hinges.numel() == 0


def test_frictionloss_on_spatial_tendon_or_slides_is_refused():
    spatial = """<mujoco><worldbody><site name="s0" pos="0 0 2"/><body pos="0 0 1"><joint type="hinge"/>
      <geom type="sphere" size="0.1"/><site name="s1"/></body></worldbody>
      <tendon><spatial name="t" frictionloss="0.1"><site site="s0"/><site site="s1"/></spatial></tendon></mujoco>"""
    with pytest.raises(UnsupportedMJCFError, match="tendon 't': frictionloss on a spatial tendon"):
        torchsim.load_mjcf(spatial)
    slide = """<mujoco><worldbody><body pos="0 0 1"><joint name="a" type="slide"/>
      <geom type="sphere" size="0.1"/></body></worldbody>
      <tendon><fixed name="t" frictionloss="0.1"><joint joint="a" coef="1"/></fixed></tendon></mujoco>"""
    with pytest.raises(UnsupportedMJCFError, match="tendon 't': frictionloss on a fixed tendon over slide joints"):
        torchsim.load_mjcf(slide)


def test_robosuite_jaco_gripper_loads_and_steps():
    """robosuite's three-finger Jaco gripper: each finger's two hinges coupled by a fixed tendon with frictionloss
    0.4 (and an equality holding it). It loads (hulls capped as the model check does), carries the three tendons'
    friction rows, and two passive steps stay finite (its loader picks 124 substeps a step; the rollout against
    MuJoCo is the model check's: PASS, ratio 0.87 with max_hull_vertices=64)."""
    sys = torchsim.load_mjcf(cached_third_party("robosuite-*/robosuite/models/assets/grippers/jaco_three_finger_gripper.xml"),
                             max_hull_vertices=64, dtype=F64)
    assert sys.ten_friction.numel() == 3 and sys.ten_friction_dof.numel() == 6
    state = torchsim.init(sys, sys.q0.expand(1, -1), torch.zeros(1, sys.nv, dtype=F64))
    for _ in range(2):
        state = torchsim.step(sys, state, torch.zeros(1, sys.nu, dtype=F64))
    assert torch.isfinite(state.q).all() and not state.diverged.any()


def test_tendon_friction_in_the_step_kernel():
    """The step kernel takes the tendon's friction rows as the reference step does: four envs from different rates,
    some slipping and some held, to 1e-9 rad over 30 steps (float64)."""
    sys = torchsim.load_mjcf(pendulum_and_wheel(0.3).replace(f'timestep="{MJ_DT}"', f'timestep="{STEP}"'), dtype=F64,
                             substeps=10)
    stepper = torchsim.Stepper(sys, "kernel", threads=1)
    rates = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 2.0], [3.0, -1.0]], dtype=F64)
    start = torchsim.init(sys, torch.zeros(4, 2, dtype=F64), rates)
    ctrl = torch.zeros(4, 0, dtype=F64)
    expected, got = start, start
    for _ in range(30):
        expected, got = torchsim.step(sys, expected, ctrl), stepper(got, ctrl)
    assert stepper.strategy == "kernel" and (expected.q - start.q).abs().max() > 0.5
    assert (got.q - expected.q).abs().max() < 1e-9


def test_tendon_friction_in_the_cuda_kernel(monkeypatch, tmp_path):
    """The same step emitted as CUDA C (one thread an env) and compiled for the host, as tests/test_strategies.py
    checks the GPU kernel: the four envs step as the reference does (1e-9 rad over 30 steps; measured 1e-14)."""
    monkeypatch.setenv("TORCHSIM_CACHE_DIR", str(tmp_path))
    sys = torchsim.load_mjcf(pendulum_and_wheel(0.3).replace(f'timestep="{MJ_DT}"', f'timestep="{STEP}"'), dtype=F64,
                             substeps=10)
    kernel = StepKernel(sys, emitter=emit_cuda)
    rates = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 2.0], [3.0, -1.0]], dtype=F64)
    start = torchsim.init(sys, torch.zeros(4, 2, dtype=F64), rates)
    ctrl = torch.zeros(4, 0, dtype=F64)
    expected, got = start, start
    for _ in range(30):
        expected, got = torchsim.step(sys, expected, ctrl), kernel(sys, got, ctrl)
    assert (expected.q - start.q).abs().max() > 0.5
    assert (got.q - expected.q).abs().max() < 1e-9
