"""Two hinges of one body at different anchors (MuJoCo lets each ``<joint>`` of a body have its own ``pos``).

MuJoCo turns a body about its hinges in order, each about its own anchor: with anchors ``p1, p2`` and rotations
``R1, R2`` (child frame = zero frame), a child point ``x`` goes to ``R1 (R2 (x - p2) + p2 - p1) + p1``. The child's
point ``p2`` thus sits at ``p1 + R1 (p2 - p1)``: it turns with the first hinge only. A joint keeps its child anchor
at ``p2`` and moves its parent anchor from ``p1`` by that offset ``e = R1 d``, ``d = p2 - p1``
(``System.jnt_anchor_offset`` holds ``d`` in the joint's axes a1, a2, a3). As the parent anchor turns with the
first hinge, the anchor constraint's Jacobian gains a term: a rotation ``w`` of the child moves its anchor away from
the parent's by ``-(r x w) - u (a1 . w)`` instead of ``-(r x w)`` (``u = a1 x e``, ``r`` the child's arm;
:func:`lever`), a rotation of the parent by minus that with the parent's arm; so a force ``F`` at the anchors turns
the child by ``r x F - (F . u) a1`` (:func:`turn_moment`; the parent by minus that). Without the extra term the
anchor force would exert a torque ``F . u`` about the first hinge: it would do work on the free motion (on a test
chain, 0.38 rad off MuJoCo within 0.5 s). ``a1 . (w_child - w_parent)`` is the first hinge's rate because the
loader requires the two axes to be orthogonal (the dual of the axes a1, a2, a1 x a2 starts with a1).

Only models with such a joint pay for this: the step skips it where ``System.jnt_has_offsets`` is False (static).
Vectors are lanes ``(3, J, B)`` unless said otherwise.
"""

import torch

from torchsim import spatial


def parent_offset(offset: torch.Tensor, a1: torch.Tensor, n12: torch.Tensor):
    """The parent anchor's offset ``e = R1 d`` [m] (world) and its rate per unit first-hinge rate ``u = a1 x e``
    [m/rad], from ``offset (3, J, 1)`` (``d`` in a1, a2, a3 components), the first hinge axis ``a1`` and the unit
    normal ``n12`` of a1 and the child's a2 (world, ``kinematics.joint_frames``).

    ``R1`` takes the zero frame's a2, a3 to ``n12 x a1`` and ``n12``: no angle (no trigonometry) is needed."""
    d1, d2, d3 = offset
    a2_turned = spatial.cross(n12, a1)
    return d1 * a1 + d2 * a2_turned + d3 * n12, d2 * n12 - d3 * a2_turned


def zero_frame_offset(offset: torch.Tensor, axes: torch.Tensor, angle: torch.Tensor):
    """``e = R1(angle) d`` and ``u = a1 x e`` [m, m/rad] in the zero frame, for ``offset (3, J, 1)`` (``d`` in axis
    components), the joint's axes ``axes (3, J, 3, 1)`` (a1..a3 along axis -2, zero frame, a3 = a1 x a2) and the
    first hinge's angle ``angle (J, B)`` [rad] (for ``kinematics.forward``)."""
    d1, d2, d3 = offset
    a1, a2, a3 = axes.unbind(-2)
    cos, sin = torch.cos(angle), torch.sin(angle)
    a2_turned, a3_turned = cos * a2 + sin * a3, cos * a3 - sin * a2
    return d1 * a1 + d2 * a2_turned + d3 * a3_turned, d2 * a3_turned - d3 * a2_turned


def lever(r: torch.Tensor, turn: torch.Tensor, a1: torch.Tensor) -> torch.Tensor:
    """``M = -[r]x - u a1^T (3, 3, ...)``: the anchor constraint's rate per unit rotation of a body with arm
    ``r (3, ...)`` to the anchor (``-[r]x`` alone for a fixed anchor), ``turn = u`` and ``a1`` ``(3, ...)``."""
    return -spatial.skew(r) - spatial.outer(turn, a1)


def turn_rate(turn: torch.Tensor, a1: torch.Tensor, ang_child: torch.Tensor, ang_parent: torch.Tensor):
    """The parent anchor's velocity from the first hinge's turning, ``u (a1 . (w_c - w_p))`` [m/s], for the bodies'
    angular velocities [rad/s]."""
    return turn * spatial.dot(a1, ang_child - ang_parent)


def turn_moment(turn: torch.Tensor, a1: torch.Tensor, force: torch.Tensor) -> torch.Tensor:
    """The moment ``-(F . u) a1`` [N m] (or angular impulse, for an impulse ``F``) that an anchor force ``F`` on the
    child adds to ``r x F``; the parent takes minus the same (it takes ``-F``)."""
    return -spatial.dot(force, turn) * a1
