"""Generalized <-> maximal coordinates against MuJoCo's own forward kinematics."""

import functools

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from models import ANT, F64, HUMANOID, METHODS, mid_range_q, quat_dist, random_q

MODELS = {"ant": ANT, "humanoid": HUMANOID}
# Everything here is float64 kinematics (a handful of quaternion products per body, depth <= 5): round-off is
# ~1e-12 (measured <= 2e-11 for velocities); 1e-6 is the brief's tolerance and still catches any wrong frame,
# axis, sign or offset, which show up at >= 1e-3.
TOL = 1e-6


@functools.lru_cache(maxsize=None)
def _sample(name):
    """torchsim init of 32 random (q, qd) and the matching MuJoCo mj_forward data."""
    path = str(MODELS[name])
    m = mujoco.MjModel.from_xml_path(path)
    d = mujoco.MjData(m)
    sys = torchsim.load_mjcf(path, dtype=F64)
    rng = np.random.default_rng(1234)
    q = random_q(m, 32, rng)
    qd = rng.normal(size=(32, m.nv))
    state = torchsim.init(sys, torch.tensor(q), torch.tensor(qd))
    ref = []
    for i in range(q.shape[0]):
        d.qpos[:], d.qvel[:] = q[i], qd[i]
        mujoco.mj_forward(m, d)
        vel = np.zeros((m.nbody, 2, 6))
        for b in range(m.nbody):
            mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_XBODY, b, vel[b, 0], 0)  # [ang, lin] at xpos
            mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_BODY, b, vel[b, 1], 0)   # [ang, lin] at the COM
        ref.append(dict(xpos=d.xpos.copy(), xquat=d.xquat.copy(), xipos=d.xipos.copy(), vel=vel))
    return m, sys, q, qd, state, ref


@pytest.mark.parametrize("name", list(MODELS))
def test_body_poses_match_mujoco(name):
    m, sys, q, qd, state, ref = _sample(name)
    xpos, xquat = torchsim.mj_body_poses(sys, state.x_pos, state.x_quat)
    assert xpos.shape == (len(q), m.nbody, 3) and xquat.shape == (len(q), m.nbody, 4)
    mj_xpos = torch.tensor(np.stack([r["xpos"] for r in ref]))
    mj_xquat = torch.tensor(np.stack([r["xquat"] for r in ref]))
    pos_err = (xpos - mj_xpos).abs().max().item()
    quat_err = quat_dist(xquat, mj_xquat).max().item()
    print(f"{name}: xpos err {pos_err:.2e}, xquat err {quat_err:.2e}")
    assert pos_err < TOL and quat_err < TOL


@pytest.mark.parametrize("name", list(MODELS))
def test_com_and_velocities_match_mujoco(name):
    """x_pos is the COM of each fused (weld) group; xd_vel its velocity, xd_ang the group's angular velocity."""
    m, sys, q, qd, state, ref = _sample(name)
    roots = [b for b in range(1, m.nbody) if m.body_weldid[b] == b]
    assert len(roots) == sys.num_bodies
    errs = {"com": 0.0, "quat": 0.0, "vel_com": 0.0, "ang": 0.0}
    for i, r in enumerate(ref):
        for k, root in enumerate(roots):
            members = [b for b in range(1, m.nbody) if m.body_weldid[b] == root]
            mass = m.body_mass[members]
            com = (mass[:, None] * r["xipos"][members]).sum(0) / mass.sum()
            ang, lin_origin = r["vel"][root, 0, :3], r["vel"][root, 0, 3:]
            if len(members) == 1:
                vel_com = r["vel"][root, 1, 3:]  # mjOBJ_BODY: the body's COM, world frame
            else:  # fused group: rigid-body transfer from the root's frame origin to the group COM
                vel_com = lin_origin + np.cross(ang, com - r["xpos"][root])
            errs["com"] = max(errs["com"], np.abs(state.x_pos[i, k].numpy() - com).max())
            errs["quat"] = max(errs["quat"], quat_dist(state.x_quat[i, k], torch.tensor(r["xquat"][root])).item())
            errs["vel_com"] = max(errs["vel_com"], np.abs(state.xd_vel[i, k].numpy() - vel_com).max())
            errs["ang"] = max(errs["ang"], np.abs(state.xd_ang[i, k].numpy() - ang).max())
    print(f"{name}: {errs}")
    assert max(errs.values()) < TOL, errs


@pytest.mark.parametrize("name", list(MODELS))
def test_init_reads_back_q_qd(name):
    m, sys, q, qd, state, _ = _sample(name)
    q, qd = torch.tensor(q), torch.tensor(qd)
    hinge = torch.ones(m.nq, dtype=torch.bool)
    hinge[3:7] = False  # the free joint's quaternion is compared up to sign
    q_err = (state.q[:, hinge] - q[:, hinge]).abs().max().item()
    quat_err = quat_dist(state.q[:, 3:7], q[:, 3:7]).max().item()
    qd_err = (state.qd - qd).abs().max().item()
    print(f"{name}: q err {q_err:.2e}, root quat err {quat_err:.2e}, qd err {qd_err:.2e}")
    assert q_err < TOL and quat_err < TOL and qd_err < TOL


@functools.lru_cache(maxsize=None)
def _stepped(name, method):
    """A few actuated steps in the air (no contacts) from mid-range joints and random joint velocities."""
    path = str(MODELS[name])
    m = mujoco.MjModel.from_xml_path(path)
    sys = torchsim.load_mjcf(path, method=method, dtype=F64)
    gen = torch.Generator().manual_seed(7)
    batch = 8
    q = torch.tensor(mid_range_q(m, lift=1.0)).expand(batch, -1).clone()
    qd = 0.5 * torch.randn(batch, sys.nv, generator=gen, dtype=F64)
    state = torchsim.init(sys, q, qd)
    lo, hi = sys.act_ctrl_range.unbind(-1)
    for _ in range(5):
        state = torchsim.step(sys, state, lo + (hi - lo) * torch.rand(batch, sys.nu, generator=gen, dtype=F64))
    return sys, state, torchsim.init(sys, state.q, state.qd)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("name", list(MODELS))
def test_stepped_q_roundtrip(name, method):
    """q, qd read back after stepping are a consistent coordinate set: init(q, qd) reads back the same q, qd, and
    the free root (whose read-back is exact whatever the joint errors) lands where it was."""
    sys, state, again = _stepped(name, method)
    q_err = (again.q - state.q).abs().max().item()
    qd_err = (again.qd - state.qd).abs().max().item()
    root_err = max((again.x_pos[:, 0] - state.x_pos[:, 0]).abs().max().item(),
                   quat_dist(again.x_quat[:, 0], state.x_quat[:, 0]).max().item(),
                   (again.xd_vel[:, 0] - state.xd_vel[:, 0]).abs().max().item(),
                   (again.xd_ang[:, 0] - state.xd_ang[:, 0]).abs().max().item())
    print(f"{name}/{method}: q {q_err:.2e} qd {qd_err:.2e} root {root_err:.2e} diverged {state.diverged.tolist()}")
    assert q_err < TOL and qd_err < TOL and root_err < TOL


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("name", list(MODELS))
def test_stepped_state_reinit_reproduces_poses(name, method):
    """init(sys, state.q, state.qd) after actuated steps reproduces the poses up to the joints' residuals.

    Maximal coordinates hold joints only as well as the solver does, so re-placing bodies from q moves each one
    by at most its chain's accumulated residual: anchor gap plus lever arm times axis misalignment (1 m bounds
    every lever arm of the ant and humanoid). The residuals themselves are bounded while the motors drive every
    dof at random in the air: measured xpbd 0.36 mm / 3.6e-3 rad, spring 1.1 mm / 0.025 rad (its joints are
    springs: full 150 N m on the ant's 0.04 kg legs stretches them); asserted 2 mm / 0.04 rad.
    """
    from torchsim.kinematics import joint_frames, with_world
    from torchsim.lanes import to_lanes

    sys, state, again = _stepped(name, method)
    frames = joint_frames(sys, with_world(*(to_lanes(x, 1) for x in state[:4])))
    lin_res = frames.lin_err.norm(dim=0).max().item()
    ang_res = frames.ang_err.norm(dim=0).max().item()
    pos_err = (again.x_pos - state.x_pos).abs().max().item()
    quat_err = quat_dist(again.x_quat, state.x_quat).max().item()
    print(f"{name}/{method}: x_pos {pos_err:.2e} x_quat {quat_err:.2e}; joint residuals lin {lin_res:.2e} m, "
          f"ang {ang_res:.2e}")
    assert lin_res < 2e-3 and ang_res < 0.04
    chain = len(sys.jnt_levels)  # residuals add up along a chain
    assert pos_err < chain * (lin_res + 1.0 * ang_res) and quat_err < chain * ang_res


@pytest.mark.parametrize("name", list(MODELS))
def test_substep_joint_frames_agree_on_dofs(name):
    """The substeps' short form of ``joint_frames`` (``all_slots=False``, rotations from the inverse inertias)
    measures every dof as the full form does, on poses whose joints are off by the spring method's residuals.

    The ant has single hinges only, so its short form skips the zero frame's axes a2, a3; the humanoid's 2- and
    3-hinge joints keep them. Both forms are float64 rewrites of the same geometry: round-off (~1e-14).
    """
    from torchsim import lanes, rigid
    from torchsim.kinematics import dof_hinge_rows, dof_values, joint_frames, with_world

    sys, state, _ = _stepped(name, "spring")
    bodies = with_world(*(lanes.to_lanes(x, 1) for x in state[:4]))
    rot = rigid.inverse_inertia(sys, bodies.x_quat, rigid.body_inverse_inertia(sys)).rot
    full, short = joint_frames(sys, bodies), joint_frames(sys, bodies, all_slots=False, rot=rot)
    assert full.lin_err.norm(dim=0).max() > 1e-6  # the joints are off: not a trivial check
    for field in ("q", "qd", "axes"):
        err = (dof_values(sys, getattr(full, field)) - dof_values(sys, getattr(short, field))).abs().max().item()
        assert err < 1e-12, (field, err)
    rows = [dof_hinge_rows(sys, f) for f in (full, short)]  # each dof's row of hinge_dual, as the solve reads it
    assert (rows[0] - rows[1]).abs().max().item() < 1e-12
    for field in ("r_parent", "r_child", "lin_err", "ang_err"):
        assert (getattr(full, field) - getattr(short, field)).abs().max().item() < 1e-12, field
