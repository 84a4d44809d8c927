"""Rigid-body responses shared by the solution methods: inverse inertias, and impulses exchanged by body pairs."""

from typing import NamedTuple

import torch

from torchsim import math
from torchsim.kinematics import Bodies
from torchsim.system import System


class InverseInertia(NamedTuple):
    """Ext-indexed inverse masses ``(N + 1,)`` or ``(B, N + 1)`` and world-frame inverse inertias ``(B, N + 1, 3, 3)``;
    the static world (index N) has zero of both, so impulses on it vanish. ``rot (B, N, 3, 3)``: the body rotations
    they were built for (kept for reuse)."""

    mass: torch.Tensor
    inertia: torch.Tensor
    rot: torch.Tensor


def body_inverse_inertia(sys: System) -> torch.Tensor:
    """Inverse inertia tensors in the body frames, ``(N, 3, 3)`` or ``(B, N, 3, 3)``."""
    return math.inv3(sys.body_inertia)


def inverse_inertia(sys: System, x_quat: torch.Tensor, inv_inertia_body: torch.Tensor) -> InverseInertia:
    """World-frame ``R I^-1 R^T`` for ext orientations ``x_quat (B, N + 1, 4)``."""
    rot = math.quat_to_mat(x_quat[:, :-1])
    inv_world = math.mm(rot, inv_inertia_body, rot.transpose(-1, -2))
    inv_world = torch.cat((inv_world, torch.zeros_like(inv_world[:, :1])), 1)
    inv_mass = 1.0 / sys.body_mass
    inv_mass = torch.cat((inv_mass, torch.zeros_like(inv_mass[..., :1])), -1)
    return InverseInertia(inv_mass, inv_world, rot)


def gather(inv: InverseInertia, idx: torch.Tensor):
    """Inverse mass ``(..., K, 1)`` and inverse inertia ``(B, K, 3, 3)`` of the bodies ``idx (K,)``."""
    return inv.mass.index_select(-1, idx)[..., None], inv.inertia.index_select(1, idx)


def point_inverse_mass(inv: InverseInertia, idx: torch.Tensor, r: torch.Tensor, direction: torch.Tensor):
    """Inverse mass ``(B, K)`` seen by an impulse along ``direction`` applied at arm ``r`` from the bodies' COMs."""
    m, i = gather(inv, idx)
    rn = math.cross(r, direction)
    return m[..., 0] + (rn * math.matvec(i, rn)).sum(-1)


def pair_velocity_change(inv: InverseInertia, a, b, r_a, r_b, p_lin, p_ang, scale_a=1.0, scale_b=1.0):
    """Velocity changes ``(dv, dw)`` of bodies a (``+p``) and b (``-p``) for a linear impulse ``p_lin`` at arms
    ``r_a``/``r_b`` plus an angular impulse ``p_ang``; ``scale`` averages impulses over a body's contacts."""
    ma, ia = gather(inv, a)
    mb, ib = gather(inv, b)
    dv_a = scale_a * ma * p_lin
    dw_a = scale_a * math.matvec(ia, math.cross(r_a, p_lin) + p_ang)
    dv_b = -scale_b * mb * p_lin
    dw_b = -scale_b * math.matvec(ib, math.cross(r_b, p_lin) + p_ang)
    return dv_a, dw_a, dv_b, dw_b


def scatter_pair(target: torch.Tensor, a, b, delta_a, delta_b) -> torch.Tensor:
    """Add per-pair deltas ``(B, K, ...)`` to the ext rows ``a`` and ``b`` of ``target (B, N + 1, ...)``."""
    return target.index_add(1, a, delta_a).index_add(1, b, delta_b)


def apply_pair_velocity(bodies: Bodies, inv: InverseInertia, a, b, r_a, r_b, p_lin, p_ang, scale_a=1.0, scale_b=1.0):
    """Apply impulses to the velocities of body pairs (see :func:`pair_velocity_change`)."""
    dv_a, dw_a, dv_b, dw_b = pair_velocity_change(inv, a, b, r_a, r_b, p_lin, p_ang, scale_a, scale_b)
    return bodies._replace(
        xd_vel=scatter_pair(bodies.xd_vel, a, b, dv_a, dv_b), xd_ang=scatter_pair(bodies.xd_ang, a, b, dw_a, dw_b))


def apply_pair_position(bodies: Bodies, inv: InverseInertia, a, b, r_a, r_b, p_lin, p_ang, scale_a=1.0, scale_b=1.0):
    """Apply positional impulses (XPBD corrections) to body poses: ``dx = p / m``, ``dtheta = I^-1 (r x p + p_ang)``."""
    dx_a, dth_a, dx_b, dth_b = pair_velocity_change(inv, a, b, r_a, r_b, p_lin, p_ang, scale_a, scale_b)

    def quat_delta(theta, quat):
        return 0.5 * math.quat_mul(torch.cat((torch.zeros_like(theta[..., :1]), theta), -1), quat)

    quat = scatter_pair(bodies.x_quat, a, b, quat_delta(dth_a, bodies.x_quat.index_select(1, a)),
                        quat_delta(dth_b, bodies.x_quat.index_select(1, b)))
    return bodies._replace(x_pos=scatter_pair(bodies.x_pos, a, b, dx_a, dx_b), x_quat=math.normalize(quat))


def active_count(a, b, active: torch.Tensor, num_ext: int):
    """Per-contact ``1 / (active contacts on its body)`` for bodies a and b: Jacobi averaging of contact impulses."""
    count = active.new_zeros(active.shape[0], num_ext).index_add(1, a, active).index_add(1, b, active)
    count = count.clamp_min(1.0)
    return 1.0 / count.index_select(1, a), 1.0 / count.index_select(1, b)


def dof_bodies(sys: System):
    """Child and parent ext body index ``(D,)`` of every dof."""
    joint = sys.dof_flat // 6
    return sys.jnt_child[joint], sys.jnt_parent[joint]


def dof_inverse_mass(sys: System, inv: InverseInertia, axes: torch.Tensor) -> torch.Tensor:
    """Inverse inertia ``(B, D)`` of each dof through its two bodies: ``a^T (I_c^-1 + I_p^-1) a`` for a hinge,
    ``1/m_c + 1/m_p`` for a slide (whose force acts at the child's COM)."""
    child, parent = dof_bodies(sys)
    m_c, i_c = gather(inv, child)
    m_p, i_p = gather(inv, parent)
    w_hinge = (axes * math.matvec(i_c + i_p, axes)).sum(-1)
    return torch.where(sys.dof_is_hinge, w_hinge, (m_c + m_p)[..., 0])


def dof_rate_change(sys: System, axes: torch.Tensor, before: Bodies, after: Bodies) -> torch.Tensor:
    """Change ``(B, D)`` of every dof's rate between two velocity states of the same poses."""
    child, parent = dof_bodies(sys)
    d_ang = after.xd_ang - before.xd_ang
    d_vel = after.xd_vel - before.xd_vel
    hinge = sys.dof_is_hinge[:, None]
    rel = torch.where(hinge, d_ang.index_select(1, child) - d_ang.index_select(1, parent),
                      d_vel.index_select(1, child) - d_vel.index_select(1, parent))
    return (axes * rel).sum(-1)


def apply_dof_impulse(sys: System, bodies: Bodies, inv: InverseInertia, axes: torch.Tensor, impulse: torch.Tensor,
                      position: bool) -> Bodies:
    """Apply equal and opposite impulses ``(B, D)`` along every dof (hinge: angular; slide: linear at the child's
    COM) to the velocities, or with ``position=True`` as an XPBD correction to the poses."""
    child, parent = dof_bodies(sys)
    p = impulse[..., None] * axes
    hinge = sys.dof_is_hinge[:, None]
    zero = torch.zeros_like(p)
    arm = bodies.x_pos.index_select(1, child) - bodies.x_pos.index_select(1, parent)
    apply = apply_pair_position if position else apply_pair_velocity
    return apply(bodies, inv, child, parent, zero, arm, torch.where(hinge, zero, p), torch.where(hinge, p, zero))


def dof_wrench(sys: System, bodies: Bodies, axes: torch.Tensor, tau: torch.Tensor):
    """Ext-indexed ``(force, torque)`` ``(B, N + 1, 3)`` exerting generalized forces ``tau (B, D)`` along dof ``axes
    (B, D, 3)``: a hinge torque turns child and parent against each other; a slide force pushes the child's COM
    and, equal and opposite at that same point, the parent."""
    child, parent = dof_bodies(sys)
    wrench = tau[..., None] * axes
    hinge = sys.dof_is_hinge[:, None]
    lin = torch.where(hinge, 0.0, wrench)
    ang = torch.where(hinge, wrench, 0.0)
    arm = bodies.x_pos.index_select(1, child) - bodies.x_pos.index_select(1, parent)
    zero = torch.zeros_like(bodies.x_pos)
    force = scatter_pair(zero, child, parent, lin, -lin)
    torque = scatter_pair(zero, child, parent, ang, -ang - math.cross(arm, lin))
    return force, torque
