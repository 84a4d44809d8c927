"""Spatial tendons (MuJoCo ``<tendon><spatial>``): paths through sites, their lengths and rates, and the body forces
of their tensions.

A path is a chain of straight segments between consecutive sites; a ``<pulley divisor>`` starts a branch whose
segments count ``1 / divisor`` of their length (MuJoCo's ``mj_tendon``). With ``s`` that scale, ``p0, p1`` a
segment's sites and ``u`` the unit vector from ``p0`` to ``p1``, a tendon's length is ``L = sum s |p1 - p0|`` and its
rate ``dL/dt = sum s u . (v1 - v0)``, ``v`` each site's velocity on its body. A tendon force ``f`` (positive
lengthening, as ``torchsim.tendons.forces`` gives it) does the work ``f dL/dt``: each segment pulls its second
site with ``s f u`` and its first with ``-s f u``, forces at the sites on their bodies (MuJoCo's ``ten_J^T f`` in
maximal coordinates). The bodies carry these to the joints; a segment between two sites of one body exerts no net
wrench on it.

Lanes layout (``torchsim.lanes``): ext-indexed body vectors ``(3, N + 1, B)``; per segment end ``(3, 2, S, B)``
(first ends, then second ends); per tendon ``(T, B)``.
"""

from typing import NamedTuple

import torch

from torchsim import lanes, rigid, spatial, tendons
from torchsim.kinematics import Bodies
from torchsim.system import System

#: Squared length [m^2] under which a segment's direction fades to zero: MuJoCo's ``mjMINVAL`` (1e-15 m), below which
#: it sets the direction to zero; a coincident pair of sites then pulls on nothing instead of dividing by zero.
_MIN_LENGTH_SQ = 1e-30


class Paths(NamedTuple):
    """The spatial tendons' paths at some body poses and velocities.

    Attributes:
        length: (T, B) [m] each tendon's path length (0 for fixed tendons).
        velocity: (T, B) [m/s] its rate.
        arm: (3, 2, S, B) [m] each segment's first and second site from its body's COM, world frame.
        direction: (3, S, B) unit vector from each segment's first site to its second, world frame.
    """

    length: torch.Tensor
    velocity: torch.Tensor
    arm: torch.Tensor
    direction: torch.Tensor


def paths(sys: System, bodies: Bodies) -> Paths:
    """:class:`Paths` of the spatial tendons at lanes ``bodies``. Only called for a System with them
    (``sys.ten_spatial``)."""
    ends = sys.ten_seg_body.flatten()  # (2S,): first ends, then second ends
    site = lanes.param(sys.ten_seg_pos.flatten(0, 1), 1, 1)
    arm = spatial.quat_rotate(bodies.x_quat.index_select(-2, ends), site)
    point = (bodies.x_pos.index_select(-2, ends) + arm).unflatten(-2, (2, -1))
    velocity = (bodies.xd_vel.index_select(-2, ends) + spatial.cross(bodies.xd_ang.index_select(-2, ends), arm))
    velocity = velocity.unflatten(-2, (2, -1))
    gap = point[:, 1] - point[:, 0]
    span = spatial.safe_norm(gap, _MIN_LENGTH_SQ)
    direction = gap / span
    scale = lanes.param(sys.ten_seg_scale, 1)
    rate = spatial.dot(velocity[:, 1] - velocity[:, 0], direction)
    per_tendon = span.new_zeros(sys.ten_limited.shape[0], span.shape[-1])
    return Paths(per_tendon.index_add(-2, sys.ten_seg_tendon, scale * span),
                 per_tendon.index_add(-2, sys.ten_seg_tendon, scale * rate), arm.unflatten(-2, (2, -1)), direction)


def wrench(sys: System, bodies: Bodies, path: Paths, force: torch.Tensor):
    """Ext-indexed world-frame ``(force [N], torque [N m])`` ``(3, N + 1, B)`` on every body of the tendon forces
    ``force (T, B)`` (positive lengthening) along :class:`Paths` ``path``, torques about the bodies' COMs."""
    pull = lanes.param(sys.ten_seg_scale, 1) * force.index_select(-2, sys.ten_seg_tendon) * path.direction
    on_ends = torch.stack((-pull, pull), 1)  # (3, 2, S, B): on the first site, on the second
    torque = spatial.cross(path.arm, on_ends)
    total = bodies.x_pos.new_zeros((6,) + bodies.x_pos.shape[1:])
    total = total.index_add(-2, sys.ten_seg_body.flatten(), torch.cat((on_ends, torque)).flatten(1, 2))
    return total[:3], total[3:]


def limit_wrench(sys: System, bodies: Bodies, inv: rigid.InverseInertia, force: torch.Tensor, torque: torch.Tensor,
                 axes: torch.Tensor, qd: torch.Tensor):
    """Ext-indexed world-frame ``(force [N], torque [N m])`` ``(3, N + 1, B)`` of the spatial tendons' limits on the
    bodies, given the substep's inverse inertias ``inv`` and the other forces and torques ``(3, N + 1, B)`` on the
    bodies, dof ``axes (3, D, B)`` and rates ``qd (D, B)``. Only called for a System with limited spatial tendons
    (``sys.ten_path_limits``).

    Each side of the range is MuJoCo's soft constraint with its ``a0`` term (``torchsim.tendons.limit_forces``):
    ``f = max(0, imp / A0 (aref - a0))``, MuJoCo's ``(aref - a0) / (A + R)`` where the tendon's inverse inertia
    ``A`` is ``tendon_invweight0``; ``a0`` is the acceleration the other forces and gravity give the tendon's
    length, ``sum s u . (a1 - a0)`` over its segments with the sites' accelerations on their bodies as they are
    (as ``torchsim.welds`` takes it; with the spring method the joint springs are among those forces), and the
    dofs' damping ``-b qd``, which the joint-space solve applies implicitly after these forces but MuJoCo's ``a0``
    holds (on ball_in_cup's heavily damped cup, leaving it out put the ball 13 mm off MuJoCo's path in 1 s). A string
    then holds a steady load as MuJoCo's does: without ``a0``, as the fixed tendons' limits, it would sit
    ``1 / (1 - imp)`` times as deep (20x for the default ``solimp``).
    """
    path = paths(sys, bodies)
    damping_force, damping_torque = rigid.dof_wrench(sys, bodies, axes, -lanes.param(sys.dof_damping, 1) * qd)
    force, torque = force + damping_force, torque + damping_torque
    ends = sys.ten_seg_body.flatten()
    moving = (inv.mass > 0).to(force.dtype)
    acc = (lanes.param(sys.gravity, 0, 1)[:, None] * moving + inv.mass * force).index_select(-2, ends)
    alpha = spatial.matvec(inv.inertia, torque).index_select(-2, ends)
    site_acc = (acc + spatial.cross(alpha, path.arm.flatten(1, 2))).unflatten(-2, (2, -1))
    rate_acc = lanes.param(sys.ten_seg_scale, 1) * spatial.dot(site_acc[:, 1] - site_acc[:, 0], path.direction)
    a0 = torch.zeros_like(path.length).index_add(-2, sys.ten_seg_tendon, rate_acc)
    return wrench(sys, bodies, path, tendons.limit_forces(sys, path.length, path.velocity, a0))
