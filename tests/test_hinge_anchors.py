"""Two hinges of one body at different anchors (``torchsim.hinge_anchors``) against MuJoCo on the same MJCF:
forward kinematics, reading ``q`` back, and a passive rollout; float64, eager."""

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from models import F64, METHODS, mujoco_rollout, quat_dist, rollout_errors

# A free torso; a shin on one hinge; a foot turned about a y hinge at z = .08 (with ref) then an oblique hinge at
# another point (the dm_control humanoid's ankles, moved off the foot's axis), carrying a welded toe; a toe flap on
# one more hinge. Axis a2 = (1, 0, .5) gives the anchor offset components along a1, a2 and a1 x a2.
FOOT = """
<mujoco><worldbody>
  <body name="torso" pos="0 0 1"><freejoint/><geom type="sphere" size="0.1"/>
    <body name="shin" pos="0 0 -0.1"><joint type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.04"/>
      <body name="foot" pos="0 0 -0.39" euler="10 20 30">
        <joint type="hinge" pos="0 0 .08" axis="0 1 0" ref="0.3"/>
        <joint type="hinge" pos="0.03 0.02 .04" axis="1 0 .5"/>
        <geom type="capsule" fromto="-.07 -.02 0 .14 -.04 0" size=".027"/>
        <body name="toe" pos="0.14 0 0"><geom type="sphere" size="0.03" pos="0.02 0 0"/>
          <body name="flap" pos="0.03 0 0"><joint type="hinge" axis="1 0 0"/>
            <geom type="box" size="0.02 0.02 0.005" pos="0.02 0 0"/></body>
        </body>
      </body>
    </body>
  </body></worldbody></mujoco>"""

# A pendulum whose second link hangs from two hinges at different anchors; timestep 2 ms (a short test).
CHAIN = """
<mujoco><option timestep="0.002"/><worldbody>
  <body pos="0 0 1"><joint type="hinge" axis="0 1 0"/><geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.05"/>
    <body pos="0 0 -0.5"><joint type="hinge" axis="0 1 0" pos="0 0 0.1"/>
      <joint type="hinge" axis="1 0 .5" pos="0.05 0.03 0"/>
      <geom type="capsule" fromto="0 0 0 0.1 0 -0.5" size="0.05"/>
    </body></body></worldbody></mujoco>"""


def _random_state(m, batch, rng):
    """``batch`` random (qpos, qvel) of FOOT: torso anywhere within 1 m at any orientation, hinges within +-pi."""
    q = np.tile(m.qpos0, (batch, 1))
    q[:, :3] = rng.uniform(-1, 1, (batch, 3))
    quat = rng.normal(size=(batch, 4))
    q[:, 3:7] = quat / np.linalg.norm(quat, axis=1, keepdims=True)
    q[:, 7:] = rng.uniform(-np.pi, np.pi, (batch, m.nq - 7))
    return q, rng.normal(size=(batch, m.nv))


def test_offsets_are_loaded_only_where_hinges_differ():
    """The offset is the second anchor minus the first along the joint's axes; hinges sharing one anchor get none."""
    sys = torchsim.load_mjcf(FOOT, dtype=F64)
    assert sys.jnt_has_offsets
    # foot frame: a1 = y, a2 = (1, 0, .5) / |.|; anchor offset (.03, .02, -.04) in a1, a2, a1 x a2 components
    a2 = np.array([1, 0, 0.5]) / np.linalg.norm([1, 0, 0.5])
    d = np.array([0.03, 0.02, -0.04])
    expected = [d[1], d @ a2, d @ np.cross([0, 1, 0], a2)]
    np.testing.assert_allclose(sys.jnt_anchor_offset[1].numpy(), expected, atol=1e-12)
    assert not sys.jnt_anchor_offset[[0, 2]].any()
    # the common case keeps the step as it was: no offsets, nothing to do
    shared = FOOT.replace('pos="0.03 0.02 .04" axis', 'pos="0 0 .08" axis')
    assert not torchsim.load_mjcf(shared, dtype=F64).jnt_has_offsets


def test_forward_kinematics_and_q_match_mujoco():
    """Body poses within 1e-9 of MuJoCo's xpos/xquat, COM velocities of its mj_objectVelocity, and init then
    ``state.q``, ``state.qd`` read back the q, qd given, for 16 random states (hinges over a full turn)."""
    m = mujoco.MjModel.from_xml_string(FOOT)
    d = mujoco.MjData(m)
    sys = torchsim.load_mjcf(FOOT, dtype=F64)
    q, qd = _random_state(m, 16, np.random.default_rng(7))
    state = torchsim.init(sys, torch.tensor(q), torch.tensor(qd))
    xpos, xquat = torchsim.mj_body_poses(sys, state.x_pos, state.x_quat)
    roots = [b for b in range(1, m.nbody) if m.body_weldid[b] == b]
    pos_err = quat_err = vel_err = 0.0
    for i in range(len(q)):
        d.qpos[:], d.qvel[:] = q[i], qd[i]
        mujoco.mj_forward(m, d)
        pos_err = max(pos_err, np.abs(xpos[i].numpy() - d.xpos).max())
        quat_err = max(quat_err, quat_dist(xquat[i], torch.tensor(d.xquat)).max().item())
        for k, b in enumerate(roots):
            if (m.body_weldid == b).sum() > 1:
                continue  # a fused group (foot and toe): its COM is not one MuJoCo body's
            vel = np.zeros(6)
            mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_BODY, b, vel, 0)  # [ang, lin] at the COM, world
            vel_err = max(vel_err, np.abs(state.xd_vel[i, k].numpy() - vel[3:]).max(),
                          np.abs(state.xd_ang[i, k].numpy() - vel[:3]).max())
    q_err = (state.q - torch.tensor(q)).abs().max().item()
    qd_err = (state.qd - torch.tensor(qd)).abs().max().item()
    print(f"xpos {pos_err:.1e}, xquat {quat_err:.1e}, velocities {vel_err:.1e}, q {q_err:.1e}, qd {qd_err:.1e}")
    assert max(pos_err, quat_err, vel_err, q_err, qd_err) < 1e-9
    assert torchsim.kinematics.anchor_gap(sys, state).max() < 1e-12


# Substeps of 1 ms, half the default's count, to keep the test short (~1.5 s CPU for spring, ~3 s for xpbd).
# Measured max |q - q_mujoco| over the 0.5 s: spring 0.0074 rad, xpbd 0.0085 rad, where MuJoCo at 2 ms and at 0.5 ms
# differ by 0.0055 rad (the bound is twice that). With the default 0.5 ms substeps: spring 0.0064 (and within 0.0011
# of MuJoCo at 0.1 ms), xpbd 0.0055. Without the first hinge's term in the anchor constraint (hinge_anchors.lever,
# turn_moment) both methods were off by 0.38 rad.
SUBSTEPS = 2


@pytest.mark.parametrize("method", METHODS)
def test_chain_follows_mujoco(method):
    """A 0.5 s passive swing in 3-D follows MuJoCo within twice MuJoCo's own difference between its timestep and a
    quarter of it, and the anchors stay together (< 1 mm)."""
    q0 = np.array([0.8, -0.4, 0.6])
    steps = 250
    ref, fine = (mujoco_rollout(CHAIN, q0, np.zeros(3), steps, divide) for divide in (1, 4))
    bound = 2 * np.abs(ref - fine).max()
    sys = torchsim.load_mjcf(CHAIN, method=method, substeps=SUBSTEPS, dtype=F64)
    err, gap = rollout_errors(sys, q0, np.zeros(3), ref)
    print(f"{method}: max |q - q_mujoco| {err:.2e} rad (bound {bound:.2e}), max anchor gap {gap:.1e} m")
    assert err < bound
    assert gap < 1e-3


FIRST_HINGE = '<joint type="hinge" axis="0 1 0" pos="0 0 0.1"/>'


def test_anchors_apart_after_a_slide_are_refused():
    """Two hinges at different anchors after a slide are refused by name rather than simulated wrong (3 hinges at
    different anchors load: tests/test_hinge_chains.py)."""
    with pytest.raises(torchsim.UnsupportedMJCFError, match="different anchors .* after slide joints"):
        torchsim.load_mjcf(CHAIN.replace(FIRST_HINGE, '<joint type="slide" axis="0 0 1"/>' + FIRST_HINGE), dtype=F64)
