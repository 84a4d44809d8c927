"""Hinges of one body at different anchors (MuJoCo lets each ``<joint>`` of a body have its own ``pos``).

MuJoCo turns a body about its hinges in order, each about its own anchor: with anchors ``p1 .. pn`` and rotations
``R1 .. Rn`` (child frame = zero frame), the child's point ``pn`` (the joint's child anchor, which the last hinge
does not move) sits at ``p1 + e``, ``e = R1 d1 + R1 R2 d2`` (``dk = p(k+1) - pk``; ``d2 = 0`` for 2 hinges). A
joint keeps its child anchor at ``pn`` and moves its parent anchor from ``p1`` by ``e``. As the hinges turn, ``e``
turns with them: its rate is ``T (w_child - w_parent)`` with ``T = sum_k (c_k x e_k) g_k^T`` (``c_k`` the world
axis of hinge k, ``g_k`` the row of ``JointFrames.hinge_dual`` that reads its rate off the relative rotation rate,
``e_k`` the part of ``e`` beyond hinge k), the joint's ``anchor_turn``. So the anchor constraint's Jacobian gains a
term: a rotation ``w`` of the child moves its anchor away from the parent's by ``-(r x w) - T w`` instead of
``-(r x w)`` (``r`` the child's arm; :func:`lever`), a rotation of the parent by minus that with the parent's arm;
and a force ``F`` at the anchors turns the child by ``r x F - T^T F`` (:func:`turn_moment`; the parent by minus
that). Without the extra term the anchor force would do work on the free motion (on a test chain, 0.38 rad off
MuJoCo within 0.5 s).

Two forms compute ``e`` and ``T``. 2 orthogonal hinges (``System.jnt_anchor_offset``): :func:`parent_offset`, from
the joint's frame without an angle, where ``T = (a1 x e) a1^T`` (the dual's first row is a1). Any 2 or 3 hinges
(``System.jnt_general``, ``System.jnt_anchor_steps``): :func:`chain_offset`, from the hinge angles.

Only models with such a joint pay for this: the step skips it where ``System.jnt_has_offsets`` is False (static).
Vectors are lanes ``(3, J, B)``, matrices ``(3, 3, J, B)``, unless said otherwise.
"""

import torch

from torchsim import spatial


def turn_vector(v: torch.Tensor, axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """``v (3, ...)`` rotated by ``angle (...)`` [rad] about unit ``axis (3, ...)`` (Rodrigues; any ``v``)."""
    cos, sin = torch.cos(angle), torch.sin(angle)
    return v * cos + spatial.cross(axis, v) * sin + axis * (spatial.dot(axis, v) * (1.0 - cos))


def parent_offset(offset: torch.Tensor, a1: torch.Tensor, n12: torch.Tensor):
    """The parent anchor's offset ``e = R1 d`` [m] (world) and its turn ``T = u a1^T`` [m/rad] (``u = a1 x e``),
    for 2 orthogonal hinges, from ``offset (3, J, 1)`` (``d`` in a1, a2, a3 components), the first hinge axis ``a1``
    and the unit normal ``n12`` of a1 and the child's a2 (world, ``kinematics.joint_frames``).

    ``R1`` takes the zero frame's a2, a3 to ``n12 x a1`` and ``n12``: no angle (no trigonometry) is needed."""
    d1, d2, d3 = offset
    a2_turned = spatial.cross(n12, a1)
    return d1 * a1 + d2 * a2_turned + d3 * n12, spatial.outer(d2 * n12 - d3 * a2_turned, a1)


def chain_offset(steps_world: torch.Tensor, axes: torch.Tensor, dual: torch.Tensor, q1: torch.Tensor,
                 q3: torch.Tensor):
    """The parent anchor's offset ``e`` [m] and its turn ``T`` [m/rad] (world) for 2 or 3 hinges in any layout.

    ``steps_world (3, 2, J, B)``: ``d1`` as the parent carries it (turned by the zero frame, not by the hinges) and
    ``d2`` as the child carries it (turned by all hinges; zero for 2 hinges); ``axes (3, J, 3, B)`` the hinges'
    world axes ``c1 .. c3``, ``dual (3, 3, J, B)`` their dual rows; ``q1``, ``q3 (J, B)`` the first and third hinge
    angles [rad]. ``R1 d1`` is ``d1`` turned about ``c1`` by ``q1``, ``R1 R2 d2`` the child's ``d2`` turned back
    about ``c3`` by ``-q3``."""
    c1, c2, c3 = axes.unbind(-2)
    d1, d2 = steps_world.unbind(1)
    beyond_2 = turn_vector(d2, c3, -q3)
    e = turn_vector(d1, c1, q1) + beyond_2
    return e, spatial.outer(spatial.cross(c1, e), dual[0]) + spatial.outer(spatial.cross(c2, beyond_2), dual[1])


def zero_frame_offset(offset: torch.Tensor, axes: torch.Tensor, angle: torch.Tensor):
    """``e = R1(angle) d`` and ``u = a1 x e`` [m, m/rad] in the zero frame, for ``offset (3, J, 1)`` (``d`` in axis
    components), the joint's axes ``axes (3, J, 3, 1)`` (a1..a3 along axis -2, zero frame, a3 = a1 x a2) and the
    first hinge's angle ``angle (J, B)`` [rad] (2 orthogonal hinges, for ``kinematics.forward``)."""
    d1, d2, d3 = offset
    a1, a2, a3 = axes.unbind(-2)
    cos, sin = torch.cos(angle), torch.sin(angle)
    a2_turned, a3_turned = cos * a2 + sin * a3, cos * a3 - sin * a2
    return d1 * a1 + d2 * a2_turned + d3 * a3_turned, d2 * a3_turned - d3 * a2_turned


def lever(r: torch.Tensor, turn: torch.Tensor) -> torch.Tensor:
    """``M = -[r]x - T (3, 3, ...)``: the anchor constraint's rate per unit rotation of a body with arm ``r (3, ...)``
    to the anchor (``-[r]x`` alone for a fixed anchor), for the joint's ``turn = T (3, 3, ...)``."""
    return -spatial.skew(r) - turn


def turn_rate(turn: torch.Tensor, ang_child: torch.Tensor, ang_parent: torch.Tensor) -> torch.Tensor:
    """The parent anchor's velocity from the hinges' turning, ``T (w_c - w_p)`` [m/s], for the bodies' angular
    velocities [rad/s]."""
    return spatial.matvec(turn, ang_child - ang_parent)


def turn_moment(turn: torch.Tensor, force: torch.Tensor) -> torch.Tensor:
    """The moment ``-T^T F`` [N m] (or angular impulse, for an impulse ``F``) that an anchor force ``F`` on the
    child adds to ``r x F``; the parent takes minus the same (it takes ``-F``)."""
    return -spatial.matvec(spatial.transpose(turn), force)
