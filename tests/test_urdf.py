"""URDF loading: the UR5e against pytorch-kinematics, the UR DH table and MuJoCo's own URDF import,
the URDF -> MJCF translation element by element, and the bad-input errors."""

import functools
import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import pytest
import pytorch_kinematics as pk
import torch

import torchsim
from models import F64, REPO, quat_to_mat
from torchsim.io_urdf import UnsupportedURDFError, urdf_to_mjcf
from torchsim.kinematics import anchor_gap, dof_values, joint_frames, with_world
from torchsim.lanes import from_lanes, to_lanes

UR5E = REPO / "envs" / "assets" / "ur5e.urdf"
HOME = (-np.pi / 2, -np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, 0.0)
# UR's DH table for the UR5e: (a, d, alpha) per joint.
DH = ((0.0, 0.1625, np.pi / 2), (-0.425, 0.0, 0.0), (-0.3922, 0.0, 0.0), (0.0, 0.1333, np.pi / 2),
      (0.0, 0.0997, -np.pi / 2), (0.0, 0.0996, 0.0))
# The UR5e's joints are geared; MuJoCo Menagerie models the reflected rotor inertia as armature 0.1. Without it
# the 0.365 kg wrist whips chaotically in a fall (MuJoCo at 2 ms vs 0.1 ms RK4 differs by 0.10 rad at 0.5 s).
ARMATURE = 0.1


@functools.lru_cache(maxsize=None)
def _link_names():
    """URDF link names in MuJoCo body order (body 0 is the world)."""
    m = mujoco.MjModel.from_xml_string(urdf_to_mjcf(UR5E))
    return [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b) for b in range(m.nbody)]


@functools.lru_cache(maxsize=None)
def _chain():
    return pk.build_chain_from_urdf(UR5E.read_text()).to(dtype=F64)


def _rot_angle(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Angle [rad] of the rotation between rotation matrices ``a`` and ``b`` (..., 3, 3)."""
    rel = a.transpose(-1, -2) @ b
    skew = torch.stack((rel[..., 2, 1] - rel[..., 1, 2], rel[..., 0, 2] - rel[..., 2, 0], rel[..., 1, 0] - rel[..., 0, 1]), -1)
    return torch.atan2(skew.norm(dim=-1) / 2, (rel.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2)


def _fk_errors(sys, state):
    """Max position [m] and rotation [rad] difference between every link frame of the simulated bodies and
    pytorch-kinematics' FK of the simulated joint angles ``state.q``."""
    pos, quat = torchsim.mj_body_poses(sys, state.x_pos, state.x_quat)
    fk = _chain().forward_kinematics(state.q)
    pos_err, rot_err = 0.0, 0.0
    for b, link in enumerate(_link_names()[1:], start=1):
        ref = fk[link].get_matrix()
        pos_err = max(pos_err, (pos[:, b] - ref[:, :3, 3]).norm(dim=-1).max().item())
        rot_err = max(rot_err, _rot_angle(quat_to_mat(quat[:, b]), ref[:, :3, :3]).max().item())
    return pos_err, rot_err


def test_body_poses_match_pytorch_kinematics():
    """Item 1: for 1000 random joint configurations (uniform within the limits) ``init`` places every link where
    pk's FK puts it. Measured 9.1e-8 m / 8.7e-8 rad: pk rounds every URDF ``<origin>`` to float32 (its rpy
    cos(pi/2) = -4.4e-8), ours is float64 throughout; a wrong frame, axis or sign shows at >= 1e-3."""
    sys = torchsim.load_urdf(UR5E, dtype=F64)
    lo, hi = sys.dof_range.unbind(-1)
    q = lo + (hi - lo) * torch.rand(1000, 6, generator=torch.Generator().manual_seed(0), dtype=F64)
    state = torchsim.init(sys, q, torch.zeros_like(q))
    pos_err, rot_err = _fk_errors(sys, state)
    print(f"UR5e init vs pk FK over 1000 q: {pos_err:.1e} m, {rot_err:.1e} rad")
    assert pos_err < 1e-6 and rot_err < 1e-6


def _dh_tool(q):
    """tool0 in ROS base_link from UR's DH table: base_link_inertia (UR's "base") is base_link turned by pi about z."""
    t = np.diag([-1.0, -1.0, 1.0, 1.0])
    for theta, (a, d, alpha) in zip(q, DH):
        ct, st, ca, sa = np.cos(theta), np.sin(theta), np.cos(alpha), np.sin(alpha)
        t = t @ np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0, sa, ca, d], [0, 0, 0, 1]])
    return t


@pytest.mark.parametrize("q, pos, quat", [
    (np.zeros(6), (0.8172, 0.2329, 0.0628), None),  # (-(a2 + a3), d4 + d6, d1 - d5)
    (np.array(HOME), (0.1333, -0.4919, 0.4879), (0.0, 0.0, 1.0, 0.0)),  # pointing down
])
def test_tool_frame_matches_dh_table(q, pos, quat):
    """Item 1: tool0 at q = 0 and at the home pose is UR's DH flange frame (position and orientation), and the
    fact sheet's numbers."""
    sys = torchsim.load_urdf(UR5E, dtype=F64)
    state = torchsim.init(sys, torch.tensor(q)[None], torch.zeros(1, 6, dtype=F64))
    xpos, xquat = torchsim.mj_body_poses(sys, state.x_pos, state.x_quat)
    tool = _link_names().index("tool0")
    dh = torch.tensor(_dh_tool(q))
    assert (xpos[0, tool] - dh[:3, 3]).abs().max() < 1e-12
    assert _rot_angle(quat_to_mat(xquat[0, tool]), dh[:3, :3]) < 1e-12
    assert np.allclose(xpos[0, tool].numpy(), pos, atol=1e-12)
    if quat is not None:
        assert min((xquat[0, tool] - torch.tensor(quat, dtype=F64)).abs().max(),
                   (xquat[0, tool] + torch.tensor(quat, dtype=F64)).abs().max()) < 1e-12


def _holding_torques(sys, state):
    """Joint torques that balance gravity, from the maximal-coordinate bodies: minus the generalized gravity
    force, the virtual work sum over the bodies b below joint j of (a_j x (x_b - p_j)) . m_b g."""
    frames = joint_frames(sys, with_world(*(to_lanes(x, 1) for x in state[:4])))
    axes = from_lanes(dof_values(sys, frames.axes), 1)  # (B, D, 3) world hinge axes
    anchors = state.x_pos[:, sys.jnt_child] + from_lanes(frames.r_child, 1)  # (B, J, 3); one dof per joint on this arm
    below = torch.eye(sys.num_bodies + 1, dtype=F64)  # below[j, b]: body b is in the subtree of body j
    for c, p in reversed(list(zip(sys.jnt_child.tolist(), sys.jnt_parent.tolist()))):  # children after parents
        below[p] += below[c]
    below = below[sys.jnt_child, : sys.num_bodies]
    lever = state.x_pos[:, None] - anchors[:, :, None]  # (B, J, N, 3)
    moment = torch.linalg.cross(axes[:, :, None].expand_as(lever), lever)
    return -((moment * (sys.body_mass[:, None] * sys.gravity)).sum(-1) * below).sum(-1)


def test_gravity_torques_match_mujoco():
    """Item 2: the torques that hold the arm at q = 0, from our System, equal MuJoCo's ``qfrc_bias`` for the same
    URDF and UR's numbers (-59.76 N m shoulder, -18.44 N m elbow, within 1%)."""
    m = mujoco.MjModel.from_xml_string(UR5E.read_text())
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    sys = torchsim.load_urdf(UR5E, dtype=F64)
    state = torchsim.init(sys, torch.zeros(1, 6, dtype=F64), torch.zeros(1, 6, dtype=F64))
    ours = _holding_torques(sys, state)[0].numpy()
    print(f"holding torques: ours {ours.round(4)}, MuJoCo {d.qfrc_bias.round(4)}")
    assert np.abs(ours - d.qfrc_bias).max() < 1e-9
    assert abs(ours[1] / -59.76 - 1) < 0.01 and abs(ours[2] / -18.44 - 1) < 0.01


# Measured |q| after 0.25 s holding q = 0: spring 0.010 rad, xpbd 1.2e-4 rad. The spring method's joints are springs
# whose stiffness scales with the inertia they act on (kappa I / h^2): the pan joint keeps the 0.01 kg m^2 shoulder
# link upright against the 60 N m lift reaction, so the shoulder tilts by ~7e-3 rad (16 substeps: 5.6e-4 rad).
HOLD_BOUND = {"spring": 0.012, "xpbd": 1e-3}


@pytest.mark.parametrize("method", list(HOLD_BOUND))
def test_holding_torques_keep_the_arm_still(method):
    """Item 2: the motors applying our holding torques keep the bare URDF arm (no armature) at q = 0."""
    sys = torchsim.load_urdf(UR5E, method=method, dtype=F64).replace(contact_groups=())
    state = torchsim.init(sys, torch.zeros(1, 6, dtype=F64), torch.zeros(1, 6, dtype=F64))
    ctrl = _holding_torques(sys, state)
    for _ in range(125):
        state = torchsim.step(sys, state, ctrl)
    drift = state.q.abs().max().item()
    print(f"{method}: |q| after 0.25 s of holding torques {drift:.1e} rad")
    assert drift < HOLD_BOUND[method]


def test_passive_fall_follows_mujoco():
    """Item 2: a 0.5 s fall from q = 0 with zero torque tracks MuJoCo (the URDF loaded by MuJoCo, Euler at 2 ms,
    armature 0.1 in both, no contacts) within 0.05 rad, and joint anchors stay within 1 mm.

    The arm swings through hanging straight down at ~0.45 s, where the pan is nearly free and small differences
    grow fast: MuJoCo at 2 ms vs MuJoCo at 0.1 ms RK4 differs by 0.027 rad. Measured (spring): 16 substeps
    0.029 rad, anchors 0.13 mm (asserted: 0.05 rad, about twice MuJoCo's own timestep spread); the default 4
    substeps: 0.021 rad up to 0.4 s, 0.28 rad at 0.5 s, anchors 1.2 mm.
    """
    m = mujoco.MjModel.from_xml_string(UR5E.read_text())
    m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    m.dof_armature[:] = ARMATURE
    d = mujoco.MjData(m)
    sys = torchsim.load_urdf(UR5E, armature=ARMATURE, substeps=16, dtype=F64).replace(contact_groups=())
    state = torchsim.init(sys, torch.zeros(1, 6, dtype=F64), torch.zeros(1, 6, dtype=F64))
    err, gap = 0.0, 0.0
    for _ in range(250):
        state = torchsim.step(sys, state, torch.zeros(1, 6, dtype=F64))
        mujoco.mj_step(m, d)
        diff = (state.q[0].numpy() - d.qpos + np.pi) % (2 * np.pi) - np.pi  # our hinge angles are wrapped
        err = max(err, np.abs(diff).max())
        gap = max(gap, anchor_gap(sys, state).max().item())
    print(f"passive fall: max |q - q_mujoco| {err:.3f} rad, max anchor gap {gap * 1e3:.2f} mm")
    assert err < 0.05 and gap < 1e-3


def test_pd_rollout_keeps_fk_consistent():
    """Item 3: 4 arms under PD joint targets (home +- 0.6 rad, redrawn every 0.1 s; Menagerie's gains kp 2000/500,
    kd 400/100 as position actuators, forces clipped to the URDF efforts; self-contacts on) for 200 steps: FK of the
    simulated joint angles stays on the simulated link poses within 1 mm / 1e-3 rad.

    Measured: xpbd with 4 iterations 0.37 mm / 6.5e-4 rad. The default spring method is far softer here: its joint
    springs scale with the light shoulder and upper-arm links while carrying up to 150 N m, 5.0 cm / 0.077 rad at
    4 substeps, 4.3 mm / 6.5e-3 rad at 16; xpbd with 1 iteration: 1.2 mm / 2.9e-3 rad (these three measured on 8 arms
    without contacts; docs/physics.md).
    """
    sys = torchsim.load_urdf(UR5E, method="xpbd", xpbd_iterations=4, armature=ARMATURE, dtype=F64)
    kp = torch.tensor([2000.0] * 3 + [500.0] * 3, dtype=F64)
    sys = sys.replace(act_gain=kp, act_bias=torch.stack((torch.zeros_like(kp), -kp, -kp / 5), -1),
                      act_ctrl_range=sys.dof_range, act_force_range=sys.act_ctrl_range,
                      act_force_limited=torch.ones(6, dtype=torch.bool))
    gen = torch.Generator().manual_seed(1)
    home = torch.tensor(HOME, dtype=F64).expand(4, 6)
    state = torchsim.init(sys, home.clone(), torch.zeros(4, 6, dtype=F64))
    pos_err, rot_err = 0.0, 0.0
    for i in range(200):
        if i % 50 == 0:
            target = home + 0.6 * (2 * torch.rand(4, 6, generator=gen, dtype=F64) - 1)
        state = torchsim.step(sys, state, target)
        pos_err, rot_err = (max(a, b) for a, b in zip((pos_err, rot_err), _fk_errors(sys, state)))
    print(f"PD rollout: FK(q_sim) vs link poses {pos_err * 1e3:.2f} mm, {rot_err:.1e} rad")
    assert not state.diverged.any()
    assert pos_err < 1e-3 and rot_err < 1e-3


# --- the translation, element by element, on a small URDF using what the UR5e does not -----------------------

def _urdf(joint_type="revolute", geometry='<box size="0.1 0.2 0.3"/>', extra_joint="", extra=""):
    return f"""<robot name="toy">
  <link name="base"/>
  <link name="slider">
    <inertial><origin xyz="0.1 0 0" rpy="0 0 1.5707963267948966"/><mass value="2"/>
      <inertia ixx="0.1" ixy="0" ixz="0" iyy="0.2" iyz="0" izz="0.3"/></inertial>
    <collision><origin xyz="0 0 0.5" rpy="0 0 0"/><geometry>{geometry}</geometry></collision>
  </link>
  <link name="arm">
    <inertial><mass value="1"/><inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial>
    <collision><geometry><sphere radius="0.05"/></geometry></collision>
    <collision><geometry><cylinder radius="0.02" length="0.4"/></geometry></collision>
  </link>
  <link name="weight">
    <inertial><mass value="0.5"/><inertia ixx="0.001" ixy="0" ixz="0" iyy="0.001" iyz="0" izz="0.001"/></inertial>
  </link>
  <joint name="slide" type="prismatic"><parent link="base"/><child link="slider"/>
    <origin xyz="0 0 1" rpy="0 0 0"/><axis xyz="0 2 0"/>
    <limit lower="-0.5" upper="0.5" effort="100" velocity="1"/><dynamics damping="3"/></joint>
  <joint name="spin" type="{joint_type}"><parent link="slider"/><child link="arm"/>
    <origin xyz="0.2 0 0" rpy="0.3 0.2 0.1"/><axis xyz="1 0 0"/>
    <limit lower="-1" upper="1" effort="5" velocity="1"/>{extra_joint}</joint>
  <joint name="weld" type="fixed"><parent link="arm"/><child link="weight"/><origin xyz="0 0 -0.3"/></joint>
  {extra}
</robot>"""


def test_translation_to_mjcf():
    """Each URDF element becomes the MJCF element the module docstring promises."""
    root = ET.fromstring(urdf_to_mjcf(_urdf(joint_type="continuous")))
    joints = {j.get("name"): j.attrib for j in root.iter("joint")}
    assert joints["slide"]["type"] == "slide" and joints["slide"]["axis"] == "0.0 1.0 0.0"
    assert joints["slide"]["range"] == "-0.5 0.5" and joints["slide"]["damping"] == "3.0"
    assert joints["spin"]["type"] == "hinge" and "range" not in joints["spin"]  # continuous: unlimited
    motors = {a.get("joint"): a.attrib for a in root.iter("motor")}
    assert motors["slide"]["ctrlrange"] == "-100.0 100.0" and motors["spin"]["ctrlrange"] == "-5.0 5.0"
    geoms = {g.get("name"): g.attrib for g in root.iter("geom")}
    assert geoms["slider/collision0"]["type"] == "box" and geoms["slider/collision0"]["size"] == "0.05 0.1 0.15"
    assert geoms["arm/collision1"]["type"] == "capsule" and geoms["arm/collision1"]["size"] == "0.02 0.2"
    inertial = next(b for b in root.iter("body") if b.get("name") == "slider").find("inertial").attrib
    full = np.array(inertial["fullinertia"].split(), dtype=float)  # rotated 90 deg about z: ixx <-> iyy
    assert np.allclose(full, [0.2, 0.1, 0.3, 0, 0, 0], atol=1e-12)
    # the fixed "weight" is fused into "arm"; load_urdf itself checks every link frame against pk's FK
    sys = torchsim.load_urdf(_urdf(joint_type="continuous"), dtype=F64)
    assert sys.body_names == ("slider", "arm") and np.allclose(sys.body_mass.numpy(), [2.0, 1.5])
    assert sys.dof_limited.tolist() == [True, False] and sys.dof_damping.tolist() == [3.0, 0.0]


@pytest.mark.parametrize("urdf, match", [
    (_urdf(geometry='<mesh filename="link.stl"/>'), "mesh collision geometry"),
    (_urdf(extra_joint='<mimic joint="slide"/>'), "mimic"),
    (_urdf(joint_type="floating"), "type 'floating'"),
    (_urdf(extra='<joint name="loop" type="fixed"><parent link="base"/><child link="weight"/></joint>'), "closed"),
    (_urdf(extra='<link name="stray"/>'), "one root"),
    (_urdf(extra='<joint name="x" type="fixed"><parent link="arm"/><child link="ghost"/></joint>'), "not defined"),
    (_urdf().replace('lower="-1" upper="1" ', ""), "lower 0"),
    (_urdf().replace('<axis xyz="1 0 0"/>', ""), "no <axis>"),
    ("<mujoco/>", "not a URDF"),
])
def test_bad_input_is_rejected(urdf, match):
    with pytest.raises(UnsupportedURDFError, match=match):
        torchsim.load_urdf(urdf)


def test_meshes_can_be_dropped_and_friction_warns():
    sys = torchsim.load_urdf(_urdf(geometry='<mesh filename="link.stl"/>'), ignore_meshes=True)
    assert sys.geom_body.tolist() == [1, 1]  # the slider's mesh is gone, the arm's sphere and capsule remain
    with pytest.warns(UserWarning, match="friction"):
        torchsim.load_urdf(_urdf(extra_joint='<dynamics friction="0.5"/>'))


def test_missing_file_names_the_path(tmp_path):
    missing = tmp_path / "nope.urdf"
    with pytest.raises(FileNotFoundError, match="nope.urdf"):
        torchsim.load_urdf(missing)
