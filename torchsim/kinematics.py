"""Kinematics between generalized coordinates (MuJoCo's qpos/qvel) and maximal coordinates (body poses).

``forward`` places bodies from ``q, qd`` (used by ``init``). ``joint_frames`` measures every joint from body poses:
its coordinates, velocities, world axes and constraint errors; the step uses it every substep and ``read_q``
uses it to read ``q, qd`` back.
"""

from typing import NamedTuple

import torch

from torchsim import math
from torchsim.system import System


class Bodies(NamedTuple):
    """Body poses and velocities in ext indexing: ``(B, N + 1, ...)``, the last row being the static world."""

    x_pos: torch.Tensor
    x_quat: torch.Tensor
    xd_vel: torch.Tensor
    xd_ang: torch.Tensor


class JointFrames(NamedTuple):
    """Every constrained joint measured from body poses; ``B`` envs, ``J`` joints.

    Attributes:
        q: (B, J, 6) coordinates of the 3 slide then 3 hinge slots, relative to the zero frame (no ``ref``).
        qd: (B, J, 6) their rates.
        axes: (B, J, 6, 3) world direction of each slot (slide direction or hinge axis).
        r_parent, r_child: (B, J, 3) world vectors from each body's COM to the joint anchor.
        lin_err: (B, J, 3) constrained part of the child-anchor offset from the parent anchor (world) [m].
        lin_proj: (B, J, 3, 3) world projector onto the constrained translation directions.
        ang_err: (B, J, 3) world rotation vector by which the child is rotated out of its constraint [rad].
        ang_proj: (B, J, 3, 3) world projector onto the constrained rotation directions.
        quat_rel: (B, J, 4) child orientation relative to its zero frame (a ball joint's qpos).
        ang_rel: (B, J, 3) child angular velocity relative to the parent, child frame (a ball joint's qvel).
        hinge_dual: (B, J, 3, 3) inverse of the hinge axes as columns: row k maps a relative rotation (world) onto
            hinge slot k (measured once here because the joint-space solves need it too).
    """

    q: torch.Tensor
    qd: torch.Tensor
    axes: torch.Tensor
    r_parent: torch.Tensor
    r_child: torch.Tensor
    lin_err: torch.Tensor
    lin_proj: torch.Tensor
    ang_err: torch.Tensor
    ang_proj: torch.Tensor
    quat_rel: torch.Tensor
    ang_rel: torch.Tensor
    hinge_dual: torch.Tensor


def with_world(x_pos, x_quat, xd_vel, xd_ang) -> Bodies:
    """Append the static world as body ``N`` so joints and contacts can index it like any other body."""
    b = x_pos.shape[0]
    zeros = x_pos.new_zeros(b, 1, 3)
    ident = x_quat.new_zeros(b, 1, 4)
    ident[..., 0] = 1.0
    return Bodies(
        torch.cat((x_pos, zeros), 1), torch.cat((x_quat, ident), 1),
        torch.cat((xd_vel, zeros), 1), torch.cat((xd_ang, zeros), 1),
    )


def _rotate_about(axis, v, angle):
    """Rotate ``v`` (perpendicular to unit ``axis``) by ``angle`` about ``axis``."""
    return v * torch.cos(angle)[..., None] + math.cross(axis, v) * torch.sin(angle)[..., None]


def _outer(v: torch.Tensor) -> torch.Tensor:
    return v[..., :, None] * v[..., None, :]


def joint_frames(sys: System, bodies: Bodies, joints: torch.Tensor | None = None, coordinates: bool = True) -> JointFrames:
    """Measure the joints ``joints (K,)`` (default: all) from ext body states (see :class:`JointFrames`).

    With ``coordinates=False`` only the constraint fields are computed (``q``, ``qd``, ``axes``, ``quat_rel``,
    ``ang_rel``, ``hinge_dual`` are None). Work for joint kinds absent from the model is skipped (``sys.jnt_kinds``,
    static).
    """

    def sel(t):
        return t if joints is None else t.index_select(0, joints)

    weld, one, two, three, _ = sys.jnt_kinds
    xp, qp, vp, wp = (t.index_select(1, sel(sys.jnt_parent)) for t in bodies)
    xc, qc, vc, wc = (t.index_select(1, sel(sys.jnt_child)) for t in bodies)
    quat0 = math.quat_mul(qp, sel(sys.jnt_quat0))  # zero frame of the child, in the world
    r_parent = math.quat_rotate(qp, sel(sys.jnt_anchor_parent))
    r_child = math.quat_rotate(qc, sel(sys.jnt_anchor_child))
    delta = (xc + r_child) - (xp + r_parent)
    mode = sel(sys.jnt_mode)[..., None]  # (J, 5, 1): weld, 1, 2, 3 hinges, ball
    axes = sel(sys.jnt_axes)
    a1, a2, a3 = axes.unbind(-2)
    axes0 = math.quat_rotate(quat0.unsqueeze(-2), axes)  # (B, J, 3, 3): a1..a3 in the zero frame, world
    axes_c = math.quat_rotate(qc.unsqueeze(-2), axes)  # a1..a3 turning with the child, world
    eye = math.eye3(xp)
    zero3 = torch.zeros_like(delta)

    # constraint errors: the anchor offset along constrained directions, and the rotation out of the hinge axes
    if sys.jnt_has_slides:
        rot0 = math.quat_to_mat(quat0)
        lin_proj = math.mm(rot0, sel(sys.jnt_lin_proj), rot0.transpose(-1, -2))
        lin_err = math.matvec(lin_proj, delta)
    else:
        lin_proj, lin_err = eye.expand(delta.shape + (3,)), delta
    a1_w, a2_c = axes0[..., 0, :], axes_c[..., 1, :]
    ang_err, ang_proj = zero3, torch.zeros_like(lin_proj)
    if weld:
        ang_err = ang_err + mode[:, 0] * math.quat_to_rot_vec(math.quat_mul(qc, math.quat_conj(quat0)))
        ang_proj = ang_proj + mode[:, 0, None] * eye
    if one:
        ang_err = ang_err + mode[:, 1] * math.cross(a1_w, axes_c[..., 0, :])
        ang_proj = ang_proj + mode[:, 1, None] * (eye - _outer(a1_w))
    n12 = math.normalize(math.cross(a1_w, a2_c)) if two else zero3
    if two:
        tilt = torch.asin(torch.clamp(math.dot(a1_w, a2_c), -1.0, 1.0))
        ang_err = ang_err - mode[:, 2] * tilt * n12
        ang_proj = ang_proj + mode[:, 2, None] * _outer(n12)
    if not coordinates:
        return JointFrames(None, None, None, r_parent, r_child, lin_err, lin_proj, ang_err, ang_proj,
                           None, None, None)

    # hinge coordinates: decompose the relative rotation about the joint's axes (a1 parent-fixed, last child-fixed)
    quat_rel = math.quat_mul(math.quat_conj(quat0), qc)
    ang_rel_w = wc - wp
    r_a2 = math.quat_rotate(quat_rel, a2)
    rt_a1 = math.quat_rotate_inv(quat_rel, a1)
    q1 = (mode[:, 1, 0] + mode[:, 2, 0]) * math.angle_about(a1, a2, r_a2)  # 1 hinge: a2 is a perpendicular of a1
    q2 = mode[:, 2, 0] * -math.angle_about(a2, a1, rt_a1) if two else q1 * 0
    q3 = q1 * 0
    hinge_axes = axes0  # rows: the zero frame's a1..a3, except where 2 or 3 hinges turn the later axes (below)
    if two or three:
        col2 = (1 - mode[:, 2] - mode[:, 3]) * axes0[..., 1, :] + mode[:, 2] * a2_c
        col3 = (1 - mode[:, 2] - mode[:, 3]) * axes0[..., 2, :] + mode[:, 2] * n12
    if three:
        handed = sel(sys.jnt_a2_sign)
        r_a3 = math.quat_rotate(quat_rel, a3)
        mid = torch.asin(torch.clamp(handed * (a1 * r_a3).sum(-1), -1.0, 1.0))
        m3 = mode[:, 3, 0]
        q1 = q1 + m3 * math.angle_about(a1, _rotate_about(a2, a3, mid), r_a3)
        q2 = q2 + m3 * mid
        q3 = m3 * -math.angle_about(a3, _rotate_about(a2, a1, -mid), rt_a1)
        a3_c = axes_c[..., 2, :]
        col2 = col2 + mode[:, 3] * handed[:, None] * math.normalize(math.cross(a3_c, a1_w))
        col3 = col3 + mode[:, 3] * a3_c
    if two or three:
        hinge_axes = torch.stack((a1_w, col2, col3), -2)
    hinge_dual = math.inv3(hinge_axes.transpose(-1, -2))
    qd_hinge = math.matvec(hinge_dual, ang_rel_w)

    # slides: the anchor offset in the zero frame, mapped onto the slide axes
    if sys.jnt_has_slides:
        d_zero = math.quat_rotate_inv(quat0, delta)
        dd_zero = math.quat_rotate_inv(
            quat0, (vc + math.cross(wc, r_child)) - (vp + math.cross(wp, r_parent)) - math.cross(wp, delta))
        q_slide = math.matvec(sel(sys.jnt_slide_pinv), d_zero)
        qd_slide = math.matvec(sel(sys.jnt_slide_pinv), dd_zero)
        slide_axes = math.quat_rotate(quat0.unsqueeze(-2), sel(sys.jnt_slide_axes))
    else:
        q_slide = qd_slide = zero3
        slide_axes = torch.zeros_like(hinge_axes)
    return JointFrames(
        q=torch.cat((q_slide, torch.stack((q1, q2, q3), -1)), -1), qd=torch.cat((qd_slide, qd_hinge), -1),
        axes=torch.cat((slide_axes, hinge_axes), -2),
        r_parent=r_parent, r_child=r_child, lin_err=lin_err, lin_proj=lin_proj, ang_err=ang_err, ang_proj=ang_proj,
        quat_rel=quat_rel, ang_rel=math.quat_rotate_inv(qc, ang_rel_w), hinge_dual=hinge_dual,
    )


def anchor_gap(sys: System, state) -> torch.Tensor:
    """Largest joint-anchor separation [m] per env ``(B,)`` of a ``torchsim.State``: the constrained part of each
    child anchor's offset from its parent anchor, the joint error that accuracy and stability checks bound."""
    bodies = with_world(state.x_pos, state.x_quat, state.xd_vel, state.xd_ang)
    return joint_frames(sys, bodies, coordinates=False).lin_err.norm(dim=-1).amax(-1)


def dof_values(sys: System, per_joint: torch.Tensor) -> torch.Tensor:
    """Gather ``(B, J, 6, ...)`` joint-slot values into ``(B, D, ...)`` dof values."""
    flat = per_joint.reshape(per_joint.shape[0], -1, *per_joint.shape[3:])
    return flat.index_select(1, sys.dof_flat)


def read_q(sys: System, bodies: Bodies, frames: JointFrames):
    """Generalized coordinates ``(B, nq)`` and velocities ``(B, nv)`` in MuJoCo's layout."""
    b = bodies.x_pos.shape[0]
    q = bodies.x_pos.new_zeros(b, sys.nq)
    qd = bodies.x_pos.new_zeros(b, sys.nv)
    q = q.index_copy(1, sys.dof_qpos, dof_values(sys, frames.q) + sys.dof_ref)
    qd = qd.index_copy(1, sys.dof_qvel, dof_values(sys, frames.qd))
    x_quat = bodies.x_quat[:, sys.free_body]
    origin = bodies.x_pos[:, sys.free_body] - math.quat_rotate(x_quat, sys.body_ipos[sys.free_body])
    ang = bodies.xd_ang[:, sys.free_body]
    lin = bodies.xd_vel[:, sys.free_body] - math.cross(ang, bodies.x_pos[:, sys.free_body] - origin)
    ang_local = math.quat_rotate_inv(x_quat, ang)
    offsets7 = torch.arange(7, device=q.device)
    offsets3 = torch.arange(3, device=q.device)
    q = q.index_copy(1, (sys.free_qpos[:, None] + offsets7).reshape(-1), torch.cat((origin, x_quat), -1).reshape(b, -1))
    qd = qd.index_copy(1, (sys.free_qvel[:, None] + torch.arange(6, device=q.device)).reshape(-1),
                       torch.cat((lin, ang_local), -1).reshape(b, -1))
    q = q.index_copy(1, (sys.ball_qpos[:, None] + offsets7[:4]).reshape(-1),
                     frames.quat_rel[:, sys.ball_joint].reshape(b, -1))
    qd = qd.index_copy(1, (sys.ball_qvel[:, None] + offsets3).reshape(-1), frames.ang_rel[:, sys.ball_joint].reshape(b, -1))
    return q, qd


def forward(sys: System, q: torch.Tensor, qd: torch.Tensor) -> Bodies:
    """Body COM poses and velocities ``(B, N, ...)`` for generalized ``q (B, nq)``, ``qd (B, nv)``, MuJoCo semantics."""
    b, n = q.shape[0], sys.num_bodies
    device = q.device
    x_pos = q.new_zeros(b, n + 1, 3)
    x_quat = q.new_zeros(b, n + 1, 4)
    x_quat[..., 0] = 1.0
    xd_vel = q.new_zeros(b, n + 1, 3)
    xd_ang = q.new_zeros(b, n + 1, 3)

    fb = sys.free_body
    offsets = torch.arange(7, device=device)
    root = q[:, sys.free_qpos[:, None] + offsets]  # (B, F, 7)
    root_vel = qd[:, sys.free_qvel[:, None] + offsets[:6]]
    quat = math.normalize(root[..., 3:])
    com = math.quat_rotate(quat, sys.body_ipos[fb])
    ang = math.quat_rotate(quat, root_vel[..., 3:])
    x_pos[:, fb] = root[..., :3] + com
    x_quat[:, fb] = quat
    xd_ang[:, fb] = ang
    xd_vel[:, fb] = root_vel[..., :3] + math.cross(ang, com)

    # joint slot values: coordinate relative to the zero frame (q - ref) and rate; ball joints read a quaternion
    n_jnt = sys.jnt_child.shape[0]
    slot_q = q.new_zeros(b, n_jnt * 6).index_copy(1, sys.dof_flat, q[:, sys.dof_qpos] - sys.dof_ref).view(b, n_jnt, 6)
    slot_qd = q.new_zeros(b, n_jnt * 6).index_copy(1, sys.dof_flat, qd[:, sys.dof_qvel]).view(b, n_jnt, 6)
    ball_q = q.new_zeros(b, n_jnt, 4)
    ball_q[..., 0] = 1.0
    ball_q[:, sys.ball_joint] = math.normalize(q[:, sys.ball_qpos[:, None] + offsets[:4]])
    ball_qd = q.new_zeros(b, n_jnt, 3)
    ball_qd[:, sys.ball_joint] = qd[:, sys.ball_qvel[:, None] + offsets[:3]]

    for level in sys.jnt_levels:
        p, c = sys.jnt_parent[level], sys.jnt_child[level]
        xp, qp, vp, wp = x_pos[:, p], x_quat[:, p], xd_vel[:, p], xd_ang[:, p]
        quat0 = math.quat_mul(qp, sys.jnt_quat0[level])
        sq, sqd = slot_q[:, level], slot_qd[:, level]
        # hinges compose about a1, a2, a3 in order (unused slots have zero angle)
        rel = ball_q[:, level]
        ang_rel = xp.new_zeros(xp.shape)
        for k in range(3):
            axis = sys.jnt_axes[level, k]
            ang_rel = ang_rel + math.quat_rotate(math.quat_mul(quat0, rel), axis) * sqd[..., 3 + k, None]
            rel = math.quat_mul(rel, math.axis_angle_to_quat(axis.expand_as(xp), sq[..., 3 + k]))
        qc = math.quat_mul(quat0, rel)
        wc = wp + ang_rel + math.quat_rotate(qc, ball_qd[:, level])
        slide = math.matvec(sys.jnt_slide_axes[level].transpose(-1, -2), sq[..., :3])
        slide_rate = math.matvec(sys.jnt_slide_axes[level].transpose(-1, -2), sqd[..., :3])
        anchor = xp + math.quat_rotate(qp, sys.jnt_anchor_parent[level]) + math.quat_rotate(quat0, slide)
        v_anchor = vp + math.cross(wp, anchor - xp) + math.quat_rotate(quat0, slide_rate)
        xc = anchor - math.quat_rotate(qc, sys.jnt_anchor_child[level])
        x_pos[:, c], x_quat[:, c], xd_ang[:, c] = xc, qc, wc
        xd_vel[:, c] = v_anchor + math.cross(wc, xc - anchor)
    return Bodies(x_pos[:, :n], x_quat[:, :n], xd_vel[:, :n], xd_ang[:, :n])


def mj_body_poses(sys: System, x_pos: torch.Tensor, x_quat: torch.Tensor):
    """World frames of every MuJoCo body (``xpos``, ``xquat``), fused ones through their parent: (B, nbody, 3|4)."""
    bodies = with_world(x_pos, x_quat, x_pos, x_pos)
    pos, quat = bodies.x_pos[:, sys.mjbody_body], bodies.x_quat[:, sys.mjbody_body]
    return pos + math.quat_rotate(quat, sys.mjbody_pos), math.quat_mul(quat, sys.mjbody_quat)
