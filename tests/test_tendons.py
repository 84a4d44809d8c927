"""Fixed tendons against MuJoCo: lengths, passive springs and dampers, soft limits, tendon-transmission actuators."""

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from torchsim import tendons
from torchsim.actuators import dof_forces
from models import F64

# A two-link pendulum (hinges h1, h2) and a separate box on a vertical slide s; {tendon} and {actuator} are filled in.
CHAIN_AND_SLIDE = """
<mujoco>
  <option timestep="{dt}" gravity="0 0 -9.81"/>
  <worldbody>
    <body pos="0 0 1"><joint name="h1" type="hinge" axis="0 1 0"/>
      <geom type="capsule" size=".05" fromto="0 0 0 .3 0 0" contype="0" conaffinity="0"/>
      <body pos=".3 0 0"><joint name="h2" type="hinge" axis="0 1 0"/>
        <geom type="capsule" size=".05" fromto="0 0 0 .3 0 0" contype="0" conaffinity="0"/>
      </body>
    </body>
    <body pos="1 0 1"><joint name="s" type="slide" axis="0 0 1"/>
      <geom type="box" size=".1 .1 .1" contype="0" conaffinity="0"/></body>
  </worldbody>
  <tendon>{tendon}</tendon>
  <actuator>{actuator}</actuator>
</mujoco>
"""
COUPLED = """<fixed name="coupled" stiffness="200" damping="5" springlength="0 0.2">
    <joint joint="h1" coef="1"/><joint joint="s" coef="-2"/></fixed>
  <fixed name="links" stiffness="5" damping="0.2" springlength="0.1 0.2">
    <joint joint="h1" coef="1"/><joint joint="h2" coef="-0.5"/></fixed>"""
Q0 = np.array([0.3, -0.8, 0.05])
#: The step [s] of the rollouts; torchsim substeps it 4 times, MuJoCo's reference takes 4 steps of a quarter of it.
STEP = 0.004


def chain(tendon: str, actuator: str = "", dt: float = STEP) -> str:
    return CHAIN_AND_SLIDE.format(dt=dt, tendon=tendon, actuator=actuator)


def mujoco_rollout(xml: str, seconds: float, substeps: int = 1, q0=Q0) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo's ``qpos`` and ``ten_length`` after each ``STEP``, stepping at the model's timestep."""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    d.qpos[:] = q0
    q, lengths = [], []
    for _ in range(round(seconds / STEP)):
        for _ in range(substeps):
            mujoco.mj_step(m, d)
        q.append(d.qpos.copy())
        lengths.append(d.ten_length.copy())
    return np.array(q), np.array(lengths)


def torchsim_rollout(xml: str, seconds: float, q0=Q0) -> np.ndarray:
    sys = torchsim.load_mjcf(xml, dtype=F64, substeps=4)
    state = torchsim.init(sys, torch.as_tensor(q0)[None], torch.zeros(1, sys.nv, dtype=F64))
    out = []
    for _ in range(round(seconds / sys.timestep)):
        state = torchsim.step(sys, state, torch.zeros(1, sys.nu, dtype=F64))
        out.append(state.q[0].numpy().copy())
    return np.array(out)


def at(sys: torchsim.System, qpos: np.ndarray) -> torch.Tensor:
    """MuJoCo ``qpos`` (or ``qvel``: hinges and slides have one of each) as dof coordinates ``(D, 1)``."""
    return torch.as_tensor(qpos)[sys.dof_qpos][:, None]


def test_length_matches_mujoco():
    xml = chain(COUPLED)
    m, sys = mujoco.MjModel.from_xml_string(xml), torchsim.load_mjcf(xml, dtype=F64)
    d = mujoco.MjData(m)
    for q in np.random.default_rng(0).uniform(-2, 2, (5, m.nq)):
        d.qpos[:] = q
        mujoco.mj_forward(m, d)
        np.testing.assert_allclose(tendons.lengths(sys, at(sys, q))[:, 0].numpy(), d.ten_length, rtol=0, atol=1e-12)
    assert sys.ten_springs and not sys.ten_limits and not sys.act_on_tendons


def test_passive_forces_and_motion_match_mujoco():
    """The generalized forces equal MuJoCo's ``qfrc_passive`` (dead band included); over 0.5 s the motion is
    within MuJoCo's own time-discretization error, its 4 ms step against 1 ms (torchsim substeps at 1 ms): measured,
    torchsim's error is a sixth to a third of that."""
    xml = chain(COUPLED)
    m, sys = mujoco.MjModel.from_xml_string(xml), torchsim.load_mjcf(xml, dtype=F64)
    d = mujoco.MjData(m)
    rng = np.random.default_rng(1)
    for _ in range(5):
        d.qpos[:], d.qvel[:] = rng.uniform(-1, 1, m.nq), rng.normal(size=m.nv)
        mujoco.mj_forward(m, d)
        tau = dof_forces(sys, at(sys, d.qpos), at(sys, d.qvel), torch.zeros(0, 1, dtype=F64))
        np.testing.assert_allclose(tau[:, 0].numpy(), d.qfrc_passive[sys.dof_qvel], rtol=1e-12, atol=1e-12)

    coarse, _ = mujoco_rollout(xml, 0.5)
    fine, _ = mujoco_rollout(chain(COUPLED, dt=STEP / 4), 0.5, substeps=4)
    ours = torchsim_rollout(xml, 0.5)
    mujoco_own = np.abs(coarse - fine).max(0)
    untensioned, _ = mujoco_rollout(chain(""), 0.5)
    assert np.all(np.abs(untensioned - fine).max(0) > 5 * mujoco_own)  # the tendons matter at this tolerance
    assert np.all(np.abs(ours - fine).max(0) < mujoco_own), (np.abs(ours - fine).max(0), mujoco_own)


LIMITED = """<fixed name="stop" limited="true" range="-0.5 0.2">
    <joint joint="h1" coef="1"/><joint joint="h2" coef="0.5"/></fixed>"""


def test_limit_holds_like_mujoco():
    """The pendulum falls from horizontal onto the upper limit of ``h1 + h2 / 2`` (0.2 rad; free, it swings past
    0.5 rad). The overshoot: MuJoCo 20 mrad (at 4 ms and 1 ms alike), torchsim 26 mrad (xpbd: 25). Pressed by the
    swinging second link, torchsim's explicit limit then sits deeper than MuJoCo's: after 0.3 s 14 mrad against
    1.4 mrad, as it leaves out MuJoCo's ``a0`` term (``torchsim.tendons``: ``1 - imp`` = 5 % of ours)."""
    q0, hi = np.zeros(3), 0.2
    seconds = 0.3  # the second link stays within (-pi, pi)
    _, reference = mujoco_rollout(chain(LIMITED, dt=STEP / 4), seconds, substeps=4, q0=q0)
    free, _ = mujoco_rollout(chain(""), seconds, q0=q0)
    q = torchsim_rollout(chain(LIMITED), seconds, q0=q0)
    length = q[:, 0] + 0.5 * q[:, 1]
    assert (free[:, 0] + 0.5 * free[:, 1]).max() > 0.5
    overshoot, mujoco_overshoot = length.max() - hi, reference[:, 0].max() - hi
    assert mujoco_overshoot < overshoot < 1.5 * mujoco_overshoot, (overshoot, mujoco_overshoot)
    assert 0 < length[-10:].mean() - hi < 0.02, length[-10:].mean()


def test_tendon_actuator_force_matches_mujoco():
    """Motor and servo (affine bias on ``gear * L`` and its rate) on tendons, next to a joint motor: the generalized
    force equals MuJoCo's ``qfrc_actuator``, controls clamped to ``ctrlrange``."""
    actuator = """<motor tendon="links" gear="2" ctrlrange="-1 1" ctrllimited="true"/>
      <position tendon="coupled" kp="30" kv="3" gear="1.5"/>
      <motor joint="h2" gear="3"/>"""
    xml = chain(COUPLED, actuator)
    m, sys = mujoco.MjModel.from_xml_string(xml), torchsim.load_mjcf(xml, dtype=F64)
    assert sys.act_on_tendons and sys.act_tendon.tolist() == [1, 0, -1]
    d = mujoco.MjData(m)
    rng = np.random.default_rng(2)
    for _ in range(5):
        d.qpos[:], d.qvel[:], d.ctrl[:] = rng.uniform(-1, 1, m.nq), rng.normal(size=m.nv), rng.uniform(-2, 2, m.nu)
        mujoco.mj_forward(m, d)
        tau = dof_forces(sys, at(sys, d.qpos), at(sys, d.qvel), torch.as_tensor(d.ctrl)[:, None])
        np.testing.assert_allclose(tau[:, 0].numpy(), (d.qfrc_actuator + d.qfrc_passive)[sys.dof_qvel], atol=1e-12)


def test_unsupported_tendon_features_are_named():
    tendon = '<fixed name="geared" armature="0.1"><joint joint="h1" coef="1"/></fixed>'
    with pytest.raises(torchsim.UnsupportedMJCFError, match="geared.*armature"):
        torchsim.load_mjcf(chain(tendon))
