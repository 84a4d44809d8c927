"""Two or three hinges of one body on non-orthogonal axes, at different anchors (``System.jnt_general``; dm_control's
dog and rodent scapulae) against MuJoCo on the same MJCF: loading, forward kinematics, reading ``q`` back and passive
rollouts; float64, eager."""

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from models import F64, METHODS, mujoco_rollout, quat_dist, rollout_errors

# The dog's left scapula (dm_control suite/dog.xml): hinges about z, x and (.287, .958, 0) (non-orthogonal), each at
# its own anchor; here under a free torso, with a ref on the first hinge, a leg on one more hinge below it, and a
# second free body whose link turns about two oblique hinges at two anchors.
SCAPULA_HINGES = """
    <joint type="hinge" axis="0 0 1" pos="-0.03 -0.02 0" ref="0.2" {extra}/>
    <joint type="hinge" axis="1 0 0" pos="0 -0.05 -0.07" {extra}/>
    <joint type="hinge" axis="0.287 0.958 0" pos="0 0 0" {extra}/>"""
# the other scapula, its third axis turned round: a1 . (a2 x a3) < 0, the other branch of Davenport's middle angle
SCAPULA_R_HINGES = """
    <joint type="hinge" axis="0 0 1" pos="-0.03 0.02 0"/>
    <joint type="hinge" axis="1 0 0" pos="0 0.05 -0.07"/>
    <joint type="hinge" axis="-0.287 -0.958 0" pos="0 0 0"/>"""
OBLIQUE_PAIR = """
    <joint type="hinge" axis="0 1 0" pos="0 0 .05" {extra}/>
    <joint type="hinge" axis="1 0.4 .5" pos="0.02 0.01 0" {extra}/>"""
BODIES = f"""
<mujoco><worldbody>
  <body name="torso" pos="0 0 1"><freejoint/><geom type="box" size="0.1 0.05 0.05"/>
    <body name="scapula" pos="0.1 0.05 -0.05" euler="10 -20 30">{SCAPULA_HINGES.format(extra="")}
      <geom type="capsule" fromto="0 0 0 0.02 0.03 -0.25" size="0.03"/>
      <body name="leg" pos="0.02 0.03 -0.25"><joint type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.2" size="0.02"/></body>
    </body>
    <body name="scapula_r" pos="0.1 -0.05 -0.05" euler="-10 -20 -30">{SCAPULA_R_HINGES}
      <geom type="capsule" fromto="0 0 0 0.02 -0.03 -0.25" size="0.03"/></body>
  </body>
  <body name="ball" pos="1 0 1"><freejoint/><geom type="sphere" size="0.05"/>
    <body name="link" pos="0 0 -0.1" euler="0 30 0">{OBLIQUE_PAIR.format(extra="")}
      <geom type="capsule" fromto="0 0 0 0.05 0 -0.2" size="0.02"/></body></body>
</worldbody></mujoco>"""


def _scene(joints: str, extra: str = "") -> str:
    """A link hanging from the world by ``joints`` (with ``extra`` attributes on each), near its rest pose at q = 0
    (its centre of mass below the anchors), 2 ms timestep."""
    return f"""
<mujoco><option timestep="0.002"/><worldbody>
  <body name="link" pos="0 0 1">{joints.format(extra=extra)}
    <geom type="capsule" fromto="0 0 0 0.03 0.02 -0.3" size="0.04"/>
  </body></worldbody></mujoco>"""


def test_general_joints_are_loaded_with_their_anchor_steps():
    """Only the scapula and the oblique pair are general; the scapula's steps are the anchors' differences (the
    first in the torso's frame, turned by the body's euler), the pair's second step is zero."""
    m = mujoco.MjModel.from_xml_string(BODIES)
    sys = torchsim.load_mjcf(BODIES, dtype=F64)
    assert sys.jnt_has_general and sys.jnt_has_offsets
    assert sys.jnt_general.tolist() == [True, False, True, True]  # scapula, leg, scapula_r, link
    scapula_in_torso = m.body_quat[m.body("scapula").id]
    turn = np.zeros(9)
    mujoco.mju_quat2Mat(turn, scapula_in_torso)
    np.testing.assert_allclose(sys.jnt_anchor_steps[0, 0].numpy(), turn.reshape(3, 3) @ [0.03, -0.03, -0.07],
                               atol=1e-12)
    np.testing.assert_allclose(sys.jnt_anchor_steps[0, 1].numpy(), [0, 0.05, 0.07], atol=1e-12)
    assert not sys.jnt_anchor_steps[1].any() and not sys.jnt_anchor_steps[3, 1].any()
    assert not sys.jnt_anchor_offset.any()  # the orthogonal 2-hinge form is not used for these


def test_forward_kinematics_and_q_match_mujoco():
    """Body poses within 1e-9 of MuJoCo's xpos/xquat, and init then ``state.q``, ``state.qd`` read back the q, qd
    given, for 16 random states (free bodies anywhere, hinges within 0.6 rad of ref, random rates). Measured:
    ~1e-12 (the angles go through acos/atan2 of dot products)."""
    m = mujoco.MjModel.from_xml_string(BODIES)
    d = mujoco.MjData(m)
    sys = torchsim.load_mjcf(BODIES, dtype=F64)
    rng = np.random.default_rng(3)
    batch = 16
    q = np.tile(m.qpos0, (batch, 1))
    for free in (0, 14):  # the torso's and the ball's qpos
        q[:, free:free + 3] = rng.uniform(-1, 1, (batch, 3))
        quat = rng.normal(size=(batch, 4))
        q[:, free + 3:free + 7] = quat / np.linalg.norm(quat, axis=1, keepdims=True)
    hinges = list(range(7, 14)) + [21, 22]
    q[:, hinges] += rng.uniform(-0.6, 0.6, (batch, len(hinges)))
    qd = rng.normal(size=(batch, m.nv))
    state = torchsim.init(sys, torch.tensor(q), torch.tensor(qd))
    xpos, xquat = torchsim.mj_body_poses(sys, state.x_pos, state.x_quat)
    pos_err = quat_err = 0.0
    for i in range(batch):
        d.qpos[:], d.qvel[:] = q[i], qd[i]
        mujoco.mj_forward(m, d)
        pos_err = max(pos_err, np.abs(xpos[i].numpy() - d.xpos).max())
        quat_err = max(quat_err, quat_dist(xquat[i], torch.tensor(d.xquat)).max().item())
    q_err = (state.q - torch.tensor(q)).abs().max().item()
    qd_err = (state.qd - torch.tensor(qd)).abs().max().item()
    print(f"xpos {pos_err:.1e}, xquat {quat_err:.1e}, q {q_err:.1e}, qd {qd_err:.1e}")
    assert max(pos_err, quat_err, q_err, qd_err) < 1e-9
    assert torchsim.kinematics.anchor_gap(sys, state).max() < 1e-10


# The spring method at 1 ms substeps (half the default's count: ~2.5 s a rollout), xpbd at the default 0.5 ms, its
# error being first order in the substep (oblique pair, against MuJoCo at dt/8: 0.0052, 0.0026, 0.00067 rad at 2,
# 4, 16 substeps; spring 0.0010, 0.00033, 0.00017). Measured max |q - q_mujoco(dt/4)| over the 0.5 s, spring /
# xpbd [rad]: scapula 0.0032 / 0.0095 (bound 0.036), scapula with springs 0.0025 / 0.0020 (bound 0.0094), oblique
# pair 0.00066 / 0.0026 (bound 0.0040). With the hinge slots' couples along the axes instead of the dual rows
# (kinematics._General), the sprung scapula was 0.13 rad off: its springs then pushed on the other hinges too;
# without the anchor's turn in the constraint (hinge_anchors.chain_offset's T), the scapula was 1.47 rad off.
SUBSTEPS = {"spring": 2, "xpbd": None}
SCENES = {
    "scapula": (_scene(SCAPULA_HINGES), [0.3, -0.2, 0.4], [0.5, -0.4, 0.6]),
    "scapula_sprung": (_scene(SCAPULA_HINGES, 'stiffness="3" damping="0.02"'), [0.3, -0.2, 0.4], [0.5, -0.4, 0.6]),
    "oblique_pair": (_scene(OBLIQUE_PAIR), [0.5, -0.3], [1.0, -1.5]),
}


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("scene", SCENES)
def test_passive_swing_follows_mujoco(scene, method):
    """A 0.5 s passive swing from start velocities follows MuJoCo at a quarter of its timestep within twice
    MuJoCo's own difference between its timestep and that quarter, and the anchors stay together (< 1 mm). The
    hinges stay away from the gimbal lock (the third axis in the plane of the first two), which a general 3-hinge
    joint does not reach while its middle hinge stays within its branch (``kinematics._general_hinges``)."""
    xml, dq0, qd0 = SCENES[scene]
    q0 = mujoco.MjModel.from_xml_string(xml).qpos0 + dq0
    steps = 250
    ref, fine = (mujoco_rollout(xml, q0, qd0, steps, divide) for divide in (1, 4))
    bound = 2 * np.abs(ref - fine).max()
    assert np.abs(fine - fine[0]).max() > 0.2  # the scene does what the test is about: the hinges turn
    sys = torchsim.load_mjcf(xml, method=method, substeps=SUBSTEPS[method], dtype=F64)
    err, gap = rollout_errors(sys, q0, qd0, fine)
    print(f"{scene} {method}: max |q - q_mujoco| {err:.2e} rad (bound {bound:.2e}), max anchor gap {gap:.1e} m")
    assert err < bound
    assert gap < 1e-3


def test_kernel_steps_the_general_joints_as_the_reference():
    """The generated C++ step (``kernel`` strategy) on the sprung scapula: the same states as the reference step by
    test_strategies' bound, no fallback (the general form's ops are inside the kernel's contract). Measured: 1.0e-12
    (the reference's own spread 2.3e-13) over 10 steps, in which the link's COM moves 0.78 mm."""
    from test_strategies import _check_against_reference

    xml, dq0, qd0 = SCENES["scapula_sprung"]
    sys = torchsim.load_mjcf(xml, dtype=F64)
    stepper = torchsim.Stepper(sys, "kernel", threads=1)
    q0 = torch.as_tensor(mujoco.MjModel.from_xml_string(xml).qpos0 + dq0)[None]
    start = torchsim.init(sys, q0, torch.tensor(qd0, dtype=F64)[None])
    _check_against_reference("general joint kernel", sys, stepper, start, torch.zeros(10, 1, 0, dtype=F64), 1, 5e-4)
    assert stepper.strategy == "kernel"


@pytest.mark.parametrize("joints, message", [
    ('<joint type="hinge" axis="0 0 1"/><joint type="hinge" axis="0 0 -2" pos="0 0.1 0"/>', "parallel hinge axes"),
    ('<joint type="hinge" axis="0 0 1"/><joint type="hinge" axis="1 0 0"/><joint type="hinge" axis="1 0 1"/>',
     "lie in one plane"),
    ('<joint type="slide" axis="0 0 1"/><joint type="hinge" axis="0 0 1"/><joint type="hinge" axis="1 0 1"/>',
     "non-orthogonal axes after slide joints"),
], ids=["parallel", "coplanar", "oblique_after_slide"])
def test_degenerate_layouts_are_refused(joints, message):
    """Hinge layouts the general form cannot represent are refused by name rather than simulated wrong."""
    with pytest.raises(torchsim.UnsupportedMJCFError, match=message):
        torchsim.load_mjcf(_scene(joints), dtype=F64)


# Three orthogonal hinges at one anchor (the humanoid's hips) keep their own form (their angles by asin), with the
# general joints' dual rows for generalized forces: along the hinge's axis instead, a motor on the last hinge also
# pushed on the first (by sin of the middle angle) and the joint went 0.029 rad off MuJoCo in 0.3 s; with the dual
# rows 1.3e-5 rad (xpbd 1.6e-5; MuJoCo's own dt vs dt/4: 4.3e-4).
MOTORED_BALL = """
<mujoco><option timestep="0.002" gravity="0 0 0"/><worldbody>
  <body name="link" pos="0 0 1">
    <joint type="hinge" axis="1 0 0"/><joint type="hinge" axis="0 0 1"/><joint name="y" type="hinge" axis="0 1 0"/>
    <geom type="capsule" fromto="0 0 0 0.03 0.02 -0.3" size="0.04"/>
  </body></worldbody><actuator><motor joint="y"/></actuator></mujoco>"""


def test_motor_on_orthogonal_three_hinges_follows_mujoco():
    """A motor on the last of 3 orthogonal hinges, middle hinge at 0.6 rad: within 2x MuJoCo's dt vs dt/4."""
    q0, steps = np.array([0.2, 0.6, 0.1]), 150
    m = mujoco.MjModel.from_xml_string(MOTORED_BALL)
    paths = []
    for divide in (1, 4):
        m.opt.timestep = 0.002 / divide
        d = mujoco.MjData(m)
        d.qpos[:], d.ctrl[:] = q0, 0.05
        paths.append([])
        for _ in range(steps):
            for _ in range(divide):
                mujoco.mj_step(m, d)
            paths[-1].append(d.qpos.copy())
    ref, fine = np.array(paths)
    sys = torchsim.load_mjcf(MOTORED_BALL, dtype=F64)
    state = torchsim.init(sys, torch.tensor(q0)[None], torch.zeros(1, 3, dtype=F64))
    ctrl = torch.full((1, 1), 0.05, dtype=F64)
    err = 0.0
    for k in range(steps):
        state = torchsim.step(sys, state, ctrl)
        err = max(err, np.abs(state.q[0].numpy() - fine[k]).max())
    assert err < 2 * np.abs(ref - fine).max()
