"""Kinematics between generalized coordinates (MuJoCo's qpos/qvel) and maximal coordinates (body poses).

``forward`` places bodies from ``q, qd`` (used by ``init``). ``joint_frames`` measures every joint from body poses:
its coordinates, velocities, world axes and constraint errors; the step uses it every substep and ``read_q``
uses it to read ``q, qd`` back. ``onto_tree`` composes the two: the articulated model's substep puts its integrated
poses back onto the joints with it.

Everything here is in the lanes layout (``torchsim.lanes``: components first, batch ``B`` last) except the public
``q, qd`` of ``read_q`` and ``forward`` and the public poses of ``anchor_gap`` and ``mj_body_poses``.
"""

from typing import NamedTuple

import torch

from torchsim import hinge_anchors, lanes, spatial
from torchsim.system import System


class Bodies(NamedTuple):
    """Body poses and velocities in ext indexing, lanes layout: ``x_pos, xd_vel, xd_ang (3, N + 1, B)``,
    ``x_quat (4, N + 1, B)``, the last body row (index ``N``) being the static world."""

    x_pos: torch.Tensor
    x_quat: torch.Tensor
    xd_vel: torch.Tensor
    xd_ang: torch.Tensor


class JointFrames(NamedTuple):
    """Every constrained joint measured from body poses, lanes layout; ``B`` envs, ``J`` joints.

    Attributes:
        q: (J, 6, B) coordinates of the 3 slide then 3 hinge slots, relative to the zero frame (no ``ref``).
        qd: (J, 6, B) their rates.
        axes: (3, J, 6, B) world direction of each slot (slide direction or hinge axis; a general joint's hinge
            slots hold its dual rows, the couples of unit generalized forces, ``_General``; see ``all_slots`` of
            :func:`joint_frames`).
        r_parent, r_child: (3, J, B) world vectors from each body's COM to the joint anchor.
        lin_err: (3, J, B) constrained part of the child-anchor offset from the parent anchor (world) [m].
        lin_proj: (3, 3, J, B) world projector onto the constrained translation directions.
        ang_err: (3, J, B) world rotation vector by which the child is rotated out of its constraint [rad].
        ang_proj: (3, 3, J, B) world projector onto the constrained rotation directions.
        quat_rel: (4, J, B) child orientation relative to its zero frame (a ball joint's qpos).
        ang_rel: (3, J, B) child angular velocity relative to the parent, child frame (a ball joint's qvel).
        hinge_dual: (3, 3, J, B) inverse of the hinge axes as columns: row ``hinge_dual[k]`` maps a relative
            rotation (world) onto hinge slot k (measured once here because the joint-space solves need it too).
        anchor_turn: (3, 3, J, B) ``T`` [m/rad]: velocity of the parent anchor per unit relative rotation rate of
            the child (world), nonzero for hinges at different anchors (``torchsim.hinge_anchors``); None where the
            model has no such joint (``System.jnt_has_offsets``).
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
    anchor_turn: torch.Tensor | None


def with_world(x_pos, x_quat, xd_vel, xd_ang) -> Bodies:
    """Append the static world as body ``N`` to lanes ``(3|4, N, B)`` poses and velocities, so joints and contacts
    can index it like any other body: :class:`Bodies` ``(3|4, N + 1, B)``."""
    b = x_pos.shape[-1]
    zeros = x_pos.new_zeros(3, 1, b)
    ident = x_quat.new_zeros(4, 1, b)
    ident[0] = 1.0
    return Bodies(
        torch.cat((x_pos, zeros), -2), torch.cat((x_quat, ident), -2),
        torch.cat((xd_vel, zeros), -2), torch.cat((xd_ang, zeros), -2),
    )


def _rotate_about(axis, v, angle):
    """Rotate ``v (3, ...)`` (perpendicular to unit ``axis``) by ``angle (...)`` about ``axis``."""
    return v * torch.cos(angle) + spatial.cross(axis, v) * torch.sin(angle)


class _Ends(NamedTuple):
    """One end (parent or child body) of each joint, lanes: ``x, vel, ang (3, J, B)``, ``quat (4, J, B)``,
    ``rot (3, 3, J, B)`` (the body's rotation matrix)."""

    x: torch.Tensor
    quat: torch.Tensor
    vel: torch.Tensor
    ang: torch.Tensor
    rot: torch.Tensor


def joint_frames(sys: System, bodies: Bodies, joints: torch.Tensor | None = None, coordinates: bool = True,
                 all_slots: bool = True, rot: torch.Tensor | None = None) -> JointFrames:
    """Measure the joints ``joints (K,)`` (default: all) from lanes ext body states (see :class:`JointFrames`;
    ``J`` there is ``K``).

    With ``coordinates=False`` only the constraint fields are computed (``q``, ``qd``, ``axes``, ``quat_rel``,
    ``ang_rel``, ``hinge_dual`` are None). With ``all_slots=False`` the hinge slots that carry no dof may come out
    zero in ``axes``, ``qd`` and ``hinge_dual``: a model without 2- and 3-hinge joints then skips the zero frame's
    axes a2, a3, which only xpbd's position solve reads. Work for joint kinds absent from the model is skipped
    (``sys.jnt_kinds``, static). ``rot (3, 3, N + 1, B)``: the bodies' rotation matrices where the caller has them
    (default: built for the joints' bodies from ``bodies.x_quat``); body-fixed vectors turn through them, at half a
    quaternion rotation's cost.
    """

    def sel(t):
        return t if joints is None else t.index_select(0, joints)

    def ends(index):
        x, quat, vel, ang = (t.index_select(-2, index) for t in bodies)
        return _Ends(x, quat, vel, ang, spatial.quat_to_mat(quat) if rot is None else rot.index_select(-2, index))

    weld, one, two, three, _ = sys.jnt_kinds
    parent, child = ends(sel(sys.jnt_parent)), ends(sel(sys.jnt_child))
    quat0_p = lanes.param(sel(sys.jnt_quat0), 1, 1)  # zero frame of the child, in the parent's frame
    quat0 = spatial.quat_mul(parent.quat, quat0_p)  # ... and in the world
    r_parent = spatial.matvec(parent.rot, lanes.param(sel(sys.jnt_anchor_parent), 1, 1))
    r_child = spatial.matvec(child.rot, lanes.param(sel(sys.jnt_anchor_child), 1, 1))
    delta = (child.x + r_child) - (parent.x + r_parent)
    mode = lanes.param(sel(sys.jnt_mode), 2, 0)  # (J, 5, 1): weld, 1, 2, 3 hinges, ball
    axes = lanes.param(sel(sys.jnt_axes), 2, 1)  # (3, J, 3, 1): a1..a3 along axis -2, zero frame (= child frame)
    axes_p = spatial.quat_rotate(quat0_p.unsqueeze(-2), axes)  # (3, J, 3, 1): a1..a3 in the parent's frame
    dof_slots_only = not (all_slots or two or three)  # then every hinge dof is a single hinge's slot a1
    if dof_slots_only:
        axes0 = None
        a1_w, a2_w = (spatial.matvec(parent.rot, axes_p[:, :, k]) for k in (0, 1))
    else:
        axes0 = spatial.matvec(parent.rot.unsqueeze(-2), axes_p)  # (3, J, 3, B): a1..a3 in the zero frame, world
        a1_w, a2_w = axes0[:, :, 0], axes0[:, :, 1]
    rot0 = spatial.quat_to_mat(quat0) if sys.jnt_has_slides else None
    a2_c = spatial.matvec(child.rot, axes[:, :, 1]) if two or coordinates else None  # a2 turning with the child
    n12 = spatial.normalize(spatial.cross(a1_w, a2_c)) if two else torch.zeros_like(delta)
    turn = None
    if sys.jnt_has_offsets:  # the parent anchor turns with the hinges (2 orthogonal ones here, general ones below)
        offset, turn = hinge_anchors.parent_offset(lanes.param(sel(sys.jnt_anchor_offset), 1, 1), a1_w, n12)
        r_parent, delta = r_parent + offset, delta - offset
    quat_rel = spatial.quat_mul(spatial.quat_conj(quat0), child.quat) if coordinates or sys.jnt_has_general else None
    general = None
    if sys.jnt_has_general:
        general = _general_hinges(sys, sel, parent, child, quat_rel, mode, axes, axes0, n12)
        is_general = lanes.param(sel(sys.jnt_general), 1, 0)  # (J, 1)
        r_parent = torch.where(is_general, r_parent + general.offset, r_parent)
        delta = torch.where(is_general, delta - general.offset, delta)
        if sys.jnt_has_offsets:
            turn = torch.where(is_general, general.turn, turn)
    constraint = _constraint_errors(sys, sel, child, quat0, rot0, delta, mode, axes, a1_w, a2_c, n12)
    if general is not None and two:  # 2 oblique hinges keep a2 at its angle to a1, not at a right angle
        tilt0 = torch.asin(torch.clamp(spatial.dot(axes[:, :, 0], axes[:, :, 1]), -1.0, 1.0))
        constraint = constraint._replace(ang_err=torch.where(
            is_general, constraint.ang_err + mode[:, 2] * tilt0 * n12, constraint.ang_err))
    if not coordinates:
        return JointFrames(None, None, None, r_parent, r_child, *constraint, None, None, None, turn)

    ang_rel_w = child.ang - parent.ang
    q_hinge, qd_hinge, hinge_axes, hinge_dual = _hinge_coordinates(
        sys, sel, child, quat_rel, ang_rel_w, mode, axes, axes0, a1_w, a2_w, a2_c, n12)
    if general is not None:  # a general joint's hinge slots hold its dual rows (_General)
        q_hinge = torch.where(is_general, general.q, q_hinge)
        hinge_dual = torch.where(is_general, general.dual, hinge_dual)
        hinge_axes = torch.where(is_general.unsqueeze(-2), hinge_dual.permute(1, 2, 0, 3), hinge_axes)
        qd_hinge = spatial.matvec(hinge_dual, ang_rel_w)
    if sys.jnt_has_slides:
        q_slide, qd_slide, slide_axes = _slide_coordinates(sys, sel, parent, child, rot0, delta, r_parent, r_child)
    else:
        q_slide = qd_slide = torch.zeros_like(delta)
        slide_axes = torch.zeros_like(hinge_axes)
    # slot values come out component-major (3, J, B); the slots of a joint go along axis -2
    return JointFrames(
        torch.cat((q_slide, q_hinge)).movedim(0, -2), torch.cat((qd_slide, qd_hinge)).movedim(0, -2),
        torch.cat((slide_axes, hinge_axes), -2), r_parent, r_child, *constraint,
        quat_rel, spatial.quat_rotate_inv(child.quat, ang_rel_w), hinge_dual, turn,
    )


class _Constraint(NamedTuple):
    lin_err: torch.Tensor
    lin_proj: torch.Tensor
    ang_err: torch.Tensor
    ang_proj: torch.Tensor


def _constraint_errors(sys, sel, child: _Ends, quat0, rot0, delta, mode, axes, a1_w, a2_c, n12) -> _Constraint:
    """The anchor offset along the constrained directions, and the rotation out of the hinge axes (the
    :class:`JointFrames` fields of those names)."""
    weld, one, two, _, _ = sys.jnt_kinds
    eye = spatial.eye3(delta, 2)
    if sys.jnt_has_slides:
        lin_proj = spatial.mm(rot0, lanes.param(sel(sys.jnt_lin_proj), 1, 2), spatial.transpose(rot0))
        lin_err = spatial.matvec(lin_proj, delta)
    else:
        lin_proj, lin_err = eye.expand((3,) + delta.shape), delta
    ang_err, ang_proj = torch.zeros_like(delta), torch.zeros_like(lin_proj)
    if weld:
        ang_err = ang_err + mode[:, 0] * spatial.quat_to_rot_vec(spatial.quat_mul(child.quat, spatial.quat_conj(quat0)))
        ang_proj = ang_proj + mode[:, 0] * eye
    if one:
        ang_err = ang_err + mode[:, 1] * spatial.cross(a1_w, spatial.matvec(child.rot, axes[:, :, 0]))
        ang_proj = ang_proj + mode[:, 1] * (eye - spatial.outer(a1_w, a1_w))
    if two:
        tilt = torch.asin(torch.clamp(spatial.dot(a1_w, a2_c), -1.0, 1.0))
        ang_err = ang_err - mode[:, 2] * tilt * n12
        ang_proj = ang_proj + mode[:, 2] * spatial.outer(n12, n12)
    return _Constraint(lin_err, lin_proj, ang_err, ang_proj)


def _hinge_coordinates(sys, sel, child: _Ends, quat_rel, ang_rel_w, mode, axes, axes0, a1_w, a2_w, a2_c, n12):
    """The hinge slots' coordinates and rates ``(3, J, B)``, world axes ``(3, J, 3, B)`` and ``hinge_dual``: the
    relative rotation decomposed about the joint's axes (a1 parent-fixed, the last child-fixed)."""
    _, _, two, three, _ = sys.jnt_kinds
    a1, a2, a3 = axes.unbind(-2)
    zero3 = torch.zeros_like(a1_w)
    # the turn about a1 taking the zero frame's a2 (a perpendicular of a1) to the child's, measured in the world
    q1 = (mode[:, 1] + mode[:, 2]) * spatial.angle_about(a1_w, a2_w, a2_c)
    q2 = q3 = torch.zeros_like(q1)
    if two or three:  # slots: the zero frame's a1..a3, except where 2 or 3 hinges turn the later axes
        rt_a1 = spatial.quat_rotate_inv(quat_rel, a1)
        q2 = mode[:, 2] * -spatial.angle_about(a2, a1, rt_a1) if two else q2
        col2 = (1 - mode[:, 2] - mode[:, 3]) * axes0[:, :, 1] + mode[:, 2] * a2_c
        col3 = (1 - mode[:, 2] - mode[:, 3]) * axes0[:, :, 2] + mode[:, 2] * n12
    if three:
        handed = lanes.param(sel(sys.jnt_a2_sign), 1, 0)
        r_a3 = spatial.quat_rotate(quat_rel, a3)
        mid = torch.asin(torch.clamp(handed * spatial.dot(a1, r_a3), -1.0, 1.0))
        m3 = mode[:, 3]
        q1 = q1 + m3 * spatial.angle_about(a1, _rotate_about(a2, a3, mid), r_a3)
        q2 = q2 + m3 * mid
        q3 = m3 * -spatial.angle_about(a3, _rotate_about(a2, a1, -mid), rt_a1)
        a3_c = spatial.matvec(child.rot, a3)
        col2 = col2 + m3 * handed * spatial.normalize(spatial.cross(a3_c, a1_w))
        col3 = col3 + m3 * a3_c
    if axes0 is None:  # slot a1 alone, the others zero: a unit axis is its own dual
        hinge_axes = torch.stack((a1_w, zero3, zero3), -2)
        hinge_dual = hinge_axes.movedim(-2, 0)
        qd_hinge = torch.stack((spatial.dot(a1_w, ang_rel_w), q2, q3))
    else:
        if two or three:
            hinge_axes = torch.stack((a1_w, col2, col3), -2)
            hinge_dual = spatial.inv3(hinge_axes.movedim(-2, 1))  # the inverse of the matrix with the axes as columns
            if three:  # a3 leaves a1's normal plane as q2 turns: generalized forces act along the dual rows (MuJoCo's
                # J^T tau), as the general joints' do (_General); a motor on a3 along a3 also pushed on a1
                hinge_axes = torch.where(mode[:, 3, None] > 0, hinge_dual.permute(1, 2, 0, 3), hinge_axes)
        else:  # the zero frame's axes are orthonormal (``System.jnt_axes``): that matrix's inverse is its transpose
            hinge_axes = axes0
            hinge_dual = hinge_axes.movedim(-2, 0)
        qd_hinge = spatial.matvec(hinge_dual, ang_rel_w)
    return torch.stack((q1, q2, q3)), qd_hinge, hinge_axes, hinge_dual


class _General(NamedTuple):
    """The general joints' (``System.jnt_general``) hinge angles ``q (3, J, B)`` [rad], dual rows ``dual (3, 3, J,
    B)``, parent-anchor offset ``offset (3, J, B)`` [m] and its ``turn (3, 3, J, B)`` [m/rad]
    (``torchsim.hinge_anchors``); other joints' values are meaningless.

    Their hinge slots' ``JointFrames.axes`` hold the dual rows ``g_k``, not the axes: a couple ``tau g_k`` on the
    child (minus it on the parent) does work ``tau`` per unit rate of hinge k alone (``g_k . c_j = delta_kj``), so
    generalized forces (springs, actuators, armature) act on the bodies as MuJoCo's ``J^T tau``. Where the axes are
    orthonormal the two coincide."""

    q: torch.Tensor
    dual: torch.Tensor
    offset: torch.Tensor
    turn: torch.Tensor


def _general_hinges(sys, sel, parent: _Ends, child: _Ends, quat_rel, mode, axes, axes0, n12) -> _General:
    """A body turned by 2 or 3 hinges on any (non-parallel, for 3 non-coplanar) axes at any anchors, in MuJoCo's
    order: ``R = R1(q1) R2(q2) R3(q3)`` (zero frame), each ``Rk`` about the body-frame axis ``ak``.

    2 hinges: ``q1`` turns the zero frame's a2 to the child's about a1, ``q2`` the child's view of a1 back to a1
    about a2. 3 hinges (Davenport's angles): ``a1 . R a3 = A cos q2 + B sin q2 + C`` (``A = a1.a3 - (a1.a2)(a2.a3)``,
    ``B = a1.(a2 x a3)``, ``C = (a1.a2)(a2.a3)``) gives ``q2`` on the branch through 0, which spans a half turn
    between the two gimbal locks (for orthogonal axes ``q2 = asin(a1 . R a3)``, the 3-hinge joints'); then ``q1``
    turns ``R2 a3`` to ``R a3`` about a1 and ``q3`` turns ``R2^T a1`` to ``R^T a1`` about a3, backwards. The world
    axes are ``c1`` (the parent's), ``c2 = R1 a2`` and ``c3`` (the child's)."""
    three = mode[:, 3] > 0  # (J, 1): 3 hinges, else 2
    a1, a2, a3 = axes.unbind(-2)  # (3, J, 1), zero frame
    a1_w, a2_w = axes0[:, :, 0], axes0[:, :, 1]
    a2_c, a3_c = (spatial.matvec(child.rot, a) for a in (a2, a3))
    rt_a1 = spatial.quat_rotate_inv(quat_rel, a1)  # a1 seen from the child
    r_a3 = spatial.quat_rotate(quat_rel, a3)  # the child's a3 in the zero frame
    k12, k23 = spatial.dot(a1, a2), spatial.dot(a2, a3)
    cos_part, sin_part = spatial.dot(a1, a3) - k12 * k23, spatial.dot(a1, spatial.cross(a2, a3))
    amplitude = torch.sqrt(cos_part * cos_part + sin_part * sin_part)
    reach = torch.clamp((spatial.dot(a1, r_a3) - k12 * k23) / amplitude, -1.0, 1.0)
    branch = torch.acos(reach)
    mid = torch.atan2(sin_part, cos_part) - torch.where(sin_part > 0, branch, -branch)
    q1 = torch.where(three, spatial.angle_about(a1, hinge_anchors.turn_vector(a3, a2, mid), r_a3),
                     spatial.angle_about(a1_w, a2_w, a2_c))
    q2 = torch.where(three, mid, -spatial.angle_about(a2, a1, rt_a1))
    q3 = torch.where(three, -spatial.angle_about(a3, hinge_anchors.turn_vector(a1, a2, -mid), rt_a1), 0.0)
    # 2 hinges: the child's a2 and the unit normal of a1 and it complete the columns (as for orthogonal ones)
    c2 = torch.where(three, hinge_anchors.turn_vector(a2_w, a1_w, q1), a2_c)
    cols = torch.stack((a1_w, c2, torch.where(three, a3_c, n12)), -2)  # (3, J, 3, B)
    dual = spatial.inv3(cols.movedim(-2, 1))
    steps = lanes.param(sel(sys.jnt_anchor_steps), 2, 1)  # (3, J, 2, 1): d1 parent frame, d2 child frame
    steps_world = torch.stack((spatial.matvec(parent.rot, steps[:, :, 0]), spatial.matvec(child.rot, steps[:, :, 1])),
                              1)
    offset, turn = hinge_anchors.chain_offset(steps_world, cols, dual, q1, q3)
    return _General(torch.stack((q1, q2, q3)), dual, offset, turn)


def _slide_coordinates(sys, sel, parent: _Ends, child: _Ends, rot0, delta, r_parent, r_child):
    """The slide slots' coordinates and rates ``(3, J, B)`` and world axes ``(3, J, 3, B)``: the anchor offset in
    the zero frame, mapped onto the slide axes."""
    slide_pinv = lanes.param(sel(sys.jnt_slide_pinv), 1, 2)
    rot0_t = spatial.transpose(rot0)
    d_zero = spatial.matvec(rot0_t, delta)
    v_child = child.vel + spatial.cross(child.ang, r_child)
    v_parent = parent.vel + spatial.cross(parent.ang, r_parent)
    dd_zero = spatial.matvec(rot0_t, v_child - v_parent - spatial.cross(parent.ang, delta))
    slide_axes = spatial.matvec(rot0.unsqueeze(-2), lanes.param(sel(sys.jnt_slide_axes), 2, 1))
    return spatial.matvec(slide_pinv, d_zero), spatial.matvec(slide_pinv, dd_zero), slide_axes


def anchor_gap(sys: System, state) -> torch.Tensor:
    """Largest joint-anchor separation [m] per env ``(B,)`` of a (public, batch-first) ``torchsim.State``: the
    constrained part of each child anchor's offset from its parent anchor, the joint error that accuracy and
    stability checks bound."""
    bodies = with_world(*(lanes.to_lanes(x, 1) for x in state[:4]))
    return torch.linalg.vector_norm(joint_frames(sys, bodies, coordinates=False).lin_err, dim=0).amax(0)


def dof_values(sys: System, per_joint: torch.Tensor) -> torch.Tensor:
    """Gather joint-slot values ``(*C, J, 6, B)`` into dof values ``(*C, D, B)``."""
    return per_joint.flatten(-3, -2).index_select(-2, sys.dof_flat)


def dof_window(sys: System, q_near: torch.Tensor) -> torch.Tensor:
    """Where a step reads dof coordinates ``(2, D, B)`` (:func:`dof_angles`): each dof's value in ``q_near (nq, B)``
    (the step's starting ``q``), its window's centre, and ``ref - centre`` less whole turns (once per step)."""
    centre = q_near.index_select(0, sys.dof_qpos)
    gap = lanes.param(sys.dof_ref, 1) - centre
    return torch.stack((centre, torch.atan2(torch.sin(gap), torch.cos(gap))))


def dof_angles(sys: System, q_zero: torch.Tensor, window: torch.Tensor) -> torch.Tensor:
    """Dof coordinates ``(D, B)`` (MuJoCo's, from ``ref``) for coordinates ``q_zero (D, B)`` measured from the zero
    frame (hinge angles in ``(-pi, pi]``), in the step's ``window`` (:func:`dof_window`).

    Body poses fix a hinge angle only within one turn. A substep takes the one nearest the hinge's ``q`` at the step's
    start, exact while a hinge turns less than half a turn per step (~300 rad/s at 10 ms): limits, springs and servos
    see ``State.q``'s continuous angle, also past pi from ``ref`` (the reacher's joint1, range +-3 rad)."""
    return in_window(q_zero, window, lanes.param(sys.dof_ref, 1), lanes.param(sys.dof_is_hinge, 1))


def in_window(q_zero: torch.Tensor, window: torch.Tensor, ref: torch.Tensor, hinge: torch.Tensor) -> torch.Tensor:
    """:func:`dof_angles` of rows ``q_zero``, with ``window (2, *rows)`` and each row's ``ref`` and whether it is a
    ``hinge`` broadcasting with them; other rows (slides, empty slots) get ``q_zero + ref``."""
    centre, shift = window.unbind(0)
    x = q_zero + shift  # in (-2 pi, 2 pi]: one turn at most takes it into (-pi, pi] (no round in the step's C++)
    x = torch.where(x > torch.pi, x - 2 * torch.pi, torch.where(x <= -torch.pi, x + 2 * torch.pi, x))
    return torch.where(hinge, centre + x, q_zero + ref)


def dof_hinge_rows(sys: System, frames: JointFrames) -> torch.Tensor:
    """Each dof's row of its joint's ``hinge_dual`` ``(3, D, B)``: the world direction that maps the joint's relative
    rotation rate onto the dof (a single hinge's axis); meaningful for hinge dofs."""
    joint = sys.dof_flat // 6
    slot = (sys.dof_flat % 6 - 3).clamp_min(0)
    # moving the row axis next to the joint axis gathers both in one index
    return spatial.transpose(frames.hinge_dual)[:, slot, joint]


def _addresses(start: torch.Tensor, width: int) -> torch.Tensor:
    """qpos/qvel addresses ``(width * K,)`` of the ``width`` consecutive values at each of ``start (K,)``, ordered
    component-major like the rows of a lanes block ``(width, K, B)`` flattened."""
    return (torch.arange(width, device=start.device)[:, None] + start).flatten()


def _block(x: torch.Tensor, start: torch.Tensor, width: int) -> torch.Tensor:
    """The ``width`` consecutive rows at each of ``start (K,)`` of lanes ``x (nq|nv, B)``: ``(width, K, B)``."""
    return x.index_select(0, _addresses(start, width)).view(width, start.shape[0], x.shape[-1])


def read_q(sys: System, bodies: Bodies, frames: JointFrames, window: torch.Tensor):
    """Generalized coordinates ``(nq, B)`` and velocities ``(nv, B)`` in MuJoCo's layout (lanes) from lanes ext
    body states and their :class:`JointFrames`.

    Body poses fix a hinge angle only up to whole turns; of those, each hinge takes the one in its ``window``
    (:func:`dof_window` of the previous step's ``q``, or of the ``q`` an env was initialised with), so hinge angles
    run on continuously through full turns, as MuJoCo's ``qpos`` does.
    """
    b = bodies.x_pos.shape[-1]
    x_pos, x_quat, xd_vel, ang = (t.index_select(-2, sys.free_body) for t in bodies)
    com = spatial.quat_rotate(x_quat, lanes.param(sys.body_ipos[sys.free_body], 1, 1))
    lin = xd_vel - spatial.cross(ang, com)
    ball = sys.ball_joint
    dof_q = dof_angles(sys, dof_values(sys, frames.q), window)
    # each part: its addresses and its lanes rows (component-major)
    q_parts = ((sys.dof_qpos, dof_q),
               (_addresses(sys.free_qpos, 7), torch.cat((x_pos - com, x_quat)).flatten(0, 1)),
               (_addresses(sys.ball_qpos, 4), frames.quat_rel.index_select(-2, ball).flatten(0, 1)))
    qd_parts = ((sys.dof_qvel, dof_values(sys, frames.qd)),
                (_addresses(sys.free_qvel, 6), torch.cat((lin, spatial.quat_rotate_inv(x_quat, ang))).flatten(0, 1)),
                (_addresses(sys.ball_qvel, 3), frames.ang_rel.index_select(-2, ball).flatten(0, 1)))
    q = x_pos.new_zeros(sys.nq, b)
    qd = x_pos.new_zeros(sys.nv, b)
    for addresses, rows in q_parts:
        q = q.index_copy(0, addresses, rows)
    for addresses, rows in qd_parts:
        qd = qd.index_copy(0, addresses, rows)
    return q, qd


def forward(sys: System, q: torch.Tensor, qd: torch.Tensor) -> Bodies:
    """Lanes body COM poses and velocities ``(3|4, N, B)`` (no world row) for public generalized ``q (B, nq)``,
    ``qd (B, nv)``, MuJoCo semantics."""
    n = sys.num_bodies
    return Bodies(*(x[:, :n] for x in forward_lanes(sys, lanes.to_lanes(q), lanes.to_lanes(qd))))


def forward_lanes(sys: System, q: torch.Tensor, qd: torch.Tensor) -> Bodies:
    """:func:`forward` for lanes ``q (nq, B)``, ``qd (nv, B)``, with the world body: ext-indexed ``(3|4, N + 1,
    B)``. Built out of place, level by level down the tree, so that the step's kernel can trace it (the articulated
    model's substep, :func:`onto_tree`)."""
    b, n = q.shape[-1], sys.num_bodies
    x_pos, xd_vel, xd_ang = (q.new_zeros(3, n + 1, b) for _ in range(3))
    x_quat = _identity_quats(q, n + 1)

    fb = sys.free_body
    root = _block(q, sys.free_qpos, 7)
    root_vel = _block(qd, sys.free_qvel, 6)
    quat = spatial.normalize(root[3:])
    com = spatial.quat_rotate(quat, lanes.param(sys.body_ipos[fb], 1, 1))
    ang = spatial.quat_rotate(quat, root_vel[3:])
    x_pos = x_pos.index_copy(1, fb, root[:3] + com)
    x_quat = x_quat.index_copy(1, fb, quat)
    xd_ang = xd_ang.index_copy(1, fb, ang)
    xd_vel = xd_vel.index_copy(1, fb, root_vel[:3] + spatial.cross(ang, com))

    # joint slot values (6, J, B): coordinate relative to the zero frame (q - ref) and rate; ball joints read a
    # quaternion
    n_jnt = sys.jnt_child.shape[0]
    dof_q = q.index_select(0, sys.dof_qpos) - lanes.param(sys.dof_ref, 1)
    slot_q = q.new_zeros(n_jnt * 6, b).index_copy(0, sys.dof_flat, dof_q).view(n_jnt, 6, b).movedim(1, 0)
    slot_qd = q.new_zeros(n_jnt * 6, b).index_copy(0, sys.dof_flat, qd.index_select(0, sys.dof_qvel))
    slot_qd = slot_qd.view(n_jnt, 6, b).movedim(1, 0)
    ball = sys.ball_joint
    ball_q = _identity_quats(q, n_jnt)
    ball_q = ball_q.index_copy(1, ball, spatial.normalize(_block(q, sys.ball_qpos, 4)))
    ball_qd = q.new_zeros(3, n_jnt, b).index_copy(1, ball, _block(qd, sys.ball_qvel, 3))

    for level in sys.jnt_levels:
        p, c = sys.jnt_parent[level], sys.jnt_child[level]
        xp, qp, vp, wp = x_pos[:, p], x_quat[:, p], xd_vel[:, p], xd_ang[:, p]
        quat0 = spatial.quat_mul(qp, lanes.param(sys.jnt_quat0[level], 1, 1))
        sq, sqd = slot_q[:, level], slot_qd[:, level]
        axes = lanes.param(sys.jnt_axes[level], 2, 1)
        # hinges compose about a1, a2, a3 in order (unused slots have zero angle)
        rel = ball_q[:, level]
        ang_rel = torch.zeros_like(xp)
        turned = []  # the zero frame turned by the first k + 1 hinges, world
        for k in range(3):
            axis = axes[:, :, k]
            ang_rel = ang_rel + spatial.quat_rotate(spatial.quat_mul(quat0, rel), axis) * sqd[3 + k]
            rel = spatial.quat_mul(rel, spatial.axis_angle_to_quat(axis, sq[3 + k]))
            if sys.jnt_has_general:
                turned.append(spatial.quat_mul(quat0, rel))
        qc = spatial.quat_mul(quat0, rel)
        wc = wp + ang_rel + spatial.quat_rotate(qc, ball_qd[:, level])
        slide_cols = spatial.transpose(lanes.param(sys.jnt_slide_axes[level], 1, 2))  # the slide axes as columns
        slide = spatial.matvec(slide_cols, sq[:3])
        slide_rate = spatial.matvec(slide_cols, sqd[:3])
        anchor_zero = xp + spatial.quat_rotate(qp, lanes.param(sys.jnt_anchor_parent[level], 1, 1))
        if sys.jnt_has_offsets:  # the parent anchor turned with the first hinge (slot 3)
            offset = lanes.param(sys.jnt_anchor_offset[level], 1, 1)
            offset, turn = hinge_anchors.zero_frame_offset(offset, axes, sq[3])
            anchor_zero = anchor_zero + spatial.quat_rotate(quat0, offset)
            slide_rate = slide_rate + turn * sqd[3]
        anchor = anchor_zero + spatial.quat_rotate(quat0, slide)
        v_anchor = vp + spatial.cross(wp, anchor - xp) + spatial.quat_rotate(quat0, slide_rate)
        if sys.jnt_has_general:  # the anchor steps d1, d2 turned by the hinges before them (hinge_anchors)
            offset, rate = _general_anchor(sys, level, qp, quat0, turned, axes, sqd[3:])
            is_general = lanes.param(sys.jnt_general[level], 1, 0)
            anchor = torch.where(is_general, anchor + offset, anchor)
            v_anchor = torch.where(is_general, v_anchor + spatial.cross(wp, offset) + rate, v_anchor)
        xc = anchor - spatial.quat_rotate(qc, lanes.param(sys.jnt_anchor_child[level], 1, 1))
        x_pos, x_quat, xd_ang = x_pos.index_copy(1, c, xc), x_quat.index_copy(1, c, qc), xd_ang.index_copy(1, c, wc)
        xd_vel = xd_vel.index_copy(1, c, v_anchor + spatial.cross(wc, xc - anchor))
    return Bodies(x_pos, x_quat, xd_vel, xd_ang)


def _identity_quats(like: torch.Tensor, count: int) -> torch.Tensor:
    """``count`` identity quaternions ``(4, count, B)`` in ``like (*, B)``'s dtype and batch (zeros plus a constant
    row, which the step's kernel folds)."""
    zeros = like.new_zeros(3, count, like.shape[-1])
    return torch.cat((zeros[:1] + 1.0, zeros))


def onto_tree(sys: System, bodies: Bodies, solved: Bodies, window: torch.Tensor) -> Bodies:
    """Lanes ``bodies`` put back onto their joints: every joint's coordinates read from the poses (:func:`read_q`,
    hinge angles in ``window``) and the bodies placed from them down the tree (:func:`forward_lanes`), each joint
    then exact. The dofs' rates are read from ``solved``, the same velocities at the poses they were solved at: read
    at the moved poses, a hinge on a turning parent would lose the square of the turn (its axis turned away)."""
    q, qd = read_q(sys, bodies, joint_frames(sys, bodies), window)
    qd = qd.index_copy(0, sys.dof_qvel, dof_values(sys, joint_frames(sys, solved, all_slots=False).qd))
    return forward_lanes(sys, q, qd)


def _general_anchor(sys: System, level, quat_parent, quat0, turned, axes, rates):
    """The general joints' parent-anchor offset ``e = R1 d1 + R1 R2 d2`` [m] and its velocity relative to the
    parent [m/s] (world), from the zero frame ``quat0``, the frames ``turned`` by the first 1, 2 hinges, the axes
    (zero frame) and the hinge ``rates (3, K, B)``, for the joints ``level`` of :func:`forward`."""
    steps = lanes.param(sys.jnt_anchor_steps[level], 2, 1)  # (3, K, 2, 1): d1 parent frame, d2 child frame
    step_1_zero = spatial.quat_rotate_inv(quat0, spatial.quat_rotate(quat_parent, steps[:, :, 0]))  # zero frame
    step_1 = spatial.quat_rotate(turned[0], step_1_zero)
    step_2 = spatial.quat_rotate(turned[1], steps[:, :, 1])
    c1 = spatial.quat_rotate(quat0, axes[:, :, 0])
    c2 = spatial.quat_rotate(turned[0], axes[:, :, 1])
    offset = step_1 + step_2
    return offset, spatial.cross(c1, offset) * rates[0] + spatial.cross(c2, step_2) * rates[1]


def mj_body_poses(sys: System, x_pos: torch.Tensor, x_quat: torch.Tensor):
    """World frames of every MuJoCo body (``xpos``, ``xquat``), fused ones through their parent, from public
    ``x_pos (B, N, 3)``, ``x_quat (B, N, 4)``: public ``(B, nbody, 3)``, ``(B, nbody, 4)`` (views of lanes
    results)."""
    pos, quat = lanes.to_lanes(x_pos, 1), lanes.to_lanes(x_quat, 1)
    bodies = with_world(pos, quat, pos, pos)
    pos, quat = bodies.x_pos.index_select(-2, sys.mjbody_body), bodies.x_quat.index_select(-2, sys.mjbody_body)
    return (lanes.from_lanes(pos + spatial.quat_rotate(quat, lanes.param(sys.mjbody_pos, 1, 1)), 1),
            lanes.from_lanes(spatial.quat_mul(quat, lanes.param(sys.mjbody_quat, 1, 1)), 1))
