"""Rigid-body responses shared by the solution methods: inverse inertias, and impulses exchanged by body pairs.

Lanes layout (``torchsim.lanes``): vectors ``(3, K, B)``, matrices ``(3, 3, K, B)``, scalar fields ``(K, B)`` over
``K`` bodies, pairs or dofs; body gathers and scatters run over axis ``-2``.

In the pair helpers ``b=None`` (with ``r_b``, ``scale_b`` and b's deltas None) stands for the static world on
every pair's b side (contacts with planes): its terms are zero, so they are skipped.
"""

from typing import NamedTuple

import torch

from torchsim import lanes, spatial
from torchsim.kinematics import Bodies
from torchsim.system import System


class InverseInertia(NamedTuple):
    """Ext-indexed inverse masses ``(N + 1, 1 | B)`` and world-frame inverse inertias ``(3, 3, N + 1, B)``; the
    static world (index N) has zero of both, so impulses on it vanish. ``rot (3, 3, N + 1, B)``: the ext body
    rotations they were built for (the world's: the identity), and ``body (3, 3, N, 1 | B)`` the body-frame inverse
    inertias they rotate (None where the world-frame ones carry more, e.g. armature), kept for reuse."""

    mass: torch.Tensor
    inertia: torch.Tensor
    rot: torch.Tensor
    body: torch.Tensor | None


def body_inverse_inertia(sys: System) -> torch.Tensor:
    """Inverse inertia tensors in the body frames, ``(3, 3, N, 1 | B)``."""
    return spatial.inv3(lanes.param(sys.body_inertia, 1, 2))


def inverse_inertia(sys: System, x_quat: torch.Tensor, inv_inertia_body: torch.Tensor) -> InverseInertia:
    """World-frame ``R I^-1 R^T`` for ext orientations ``x_quat (4, N + 1, B)`` and body-frame inverse inertias
    ``inv_inertia_body (3, 3, N, 1 | B)``."""
    rot = spatial.quat_to_mat(x_quat)
    body_rot = rot[..., :-1, :]
    inv_world = spatial.mm(body_rot, inv_inertia_body, spatial.transpose(body_rot))
    inv_world = torch.cat((inv_world, torch.zeros_like(inv_world[..., :1, :])), -2)
    inv_mass = 1.0 / lanes.param(sys.body_mass, 1)
    inv_mass = torch.cat((inv_mass, torch.zeros_like(inv_mass[:1])), -2)
    return InverseInertia(inv_mass, inv_world, rot, inv_inertia_body)


def gather(inv: InverseInertia, idx: torch.Tensor):
    """Inverse mass ``(K, 1 | B)`` and inverse inertia ``(3, 3, K, B)`` of the bodies ``idx (K,)``."""
    return inv.mass.index_select(-2, idx), inv.inertia.index_select(-2, idx)


def point_inverse_mass(inv: InverseInertia, idx: torch.Tensor, r: torch.Tensor, direction: torch.Tensor):
    """Inverse mass ``(K, B)`` seen by an impulse along ``direction (3, K, B)`` applied at arm ``r (3, K, B)`` from
    the bodies' COMs."""
    m, i = gather(inv, idx)
    rn = spatial.cross(r, direction)
    return m + spatial.dot(rn, spatial.matvec(i, rn))


def pair_inverse_mass(inv: InverseInertia, a, b, r_a, r_b, direction: torch.Tensor):
    """Inverse mass ``(K, B)`` of body pairs ``a, b (K,)`` against each other for impulses along ``direction
    (3, K, B)`` at arms ``r_a, r_b``."""
    w_a = point_inverse_mass(inv, a, r_a, direction)
    return w_a if b is None else w_a + point_inverse_mass(inv, b, r_b, direction)


def contact_arms(bodies: Bodies, a: torch.Tensor, b: torch.Tensor | None, pos: torch.Tensor):
    """Arms ``r_a, r_b (3, C, B)`` from the COMs of bodies ``a`` and ``b (C,)`` to the points ``pos (3, C, B)``, and
    the points' relative velocity ``v_rel (3, C, B)``, body a's minus body b's (``b=None``: the world)."""
    r_a = pos - bodies.x_pos.index_select(-2, a)
    v_rel = bodies.xd_vel.index_select(-2, a) + spatial.cross(bodies.xd_ang.index_select(-2, a), r_a)
    if b is None:
        return r_a, None, v_rel
    r_b = pos - bodies.x_pos.index_select(-2, b)
    v_rel = v_rel - bodies.xd_vel.index_select(-2, b) - spatial.cross(bodies.xd_ang.index_select(-2, b), r_b)
    return r_a, r_b, v_rel


def pair_velocity_change(inv: InverseInertia, a, b, r_a, r_b, p_lin, p_ang, scale_a=1.0, scale_b=1.0):
    """Velocity changes ``(dv, dw)`` ``(3, K, B)`` of bodies a (``+p``) and b (``-p``; None for ``b=None``) for a
    linear impulse ``p_lin (3, K, B)`` at arms ``r_a``/``r_b`` plus an angular impulse ``p_ang``; ``scale`` (a float
    or ``(K, B)``) averages impulses over a body's contacts."""
    ma, ia = gather(inv, a)
    dv_a = scale_a * ma * p_lin
    dw_a = scale_a * spatial.matvec(ia, spatial.cross(r_a, p_lin) + p_ang)
    if b is None:
        return dv_a, dw_a, None, None
    mb, ib = gather(inv, b)
    dv_b = -scale_b * mb * p_lin
    dw_b = -scale_b * spatial.matvec(ib, spatial.cross(r_b, p_lin) + p_ang)
    return dv_a, dw_a, dv_b, dw_b


def scatter_pair(target: torch.Tensor, a, b, delta_a, delta_b) -> torch.Tensor:
    """Add per-pair deltas ``(..., K, B)`` to the ext rows ``a`` and ``b`` of ``target (..., N + 1, B)``."""
    target = target.index_add(-2, a, delta_a)
    return target if b is None else target.index_add(-2, b, delta_b)


def apply_pair_velocity(bodies: Bodies, inv: InverseInertia, a, b, r_a, r_b, p_lin, p_ang, scale_a=1.0, scale_b=1.0):
    """Apply impulses to the velocities of body pairs (see :func:`pair_velocity_change`)."""
    dv_a, dw_a, dv_b, dw_b = pair_velocity_change(inv, a, b, r_a, r_b, p_lin, p_ang, scale_a, scale_b)
    return bodies._replace(
        xd_vel=scatter_pair(bodies.xd_vel, a, b, dv_a, dv_b), xd_ang=scatter_pair(bodies.xd_ang, a, b, dw_a, dw_b))


def apply_pair_position(bodies: Bodies, inv: InverseInertia, a, b, r_a, r_b, p_lin, p_ang, scale_a=1.0, scale_b=1.0):
    """Apply positional impulses (XPBD corrections) to body poses: ``dx = p / m``, ``dtheta = I^-1 (r x p + p_ang)``."""
    dx_a, dth_a, dx_b, dth_b = pair_velocity_change(inv, a, b, r_a, r_b, p_lin, p_ang, scale_a, scale_b)

    def quat_delta(theta, quat):
        return 0.5 * spatial.quat_mul(torch.cat((torch.zeros_like(theta[:1]), theta)), quat)

    quat = scatter_pair(bodies.x_quat, a, b, quat_delta(dth_a, bodies.x_quat.index_select(-2, a)),
                        None if b is None else quat_delta(dth_b, bodies.x_quat.index_select(-2, b)))
    return bodies._replace(x_pos=scatter_pair(bodies.x_pos, a, b, dx_a, dx_b), x_quat=spatial.normalize(quat))


def active_count(a, b, active: torch.Tensor, num_ext: int):
    """Per-contact ``1 / (active contacts on its body)`` ``(K, B)`` for bodies a and b (None for ``b=None``), from
    ``active (K, B)``: Jacobi averaging of contact impulses."""
    count = scatter_pair(active.new_zeros(num_ext, active.shape[-1]), a, b, active, active).clamp_min(1.0)
    return 1.0 / count.index_select(-2, a), None if b is None else 1.0 / count.index_select(-2, b)


def dof_bodies(sys: System):
    """Child and parent ext body index ``(D,)`` of every dof."""
    joint = sys.dof_flat // 6
    return sys.jnt_child[joint], sys.jnt_parent[joint]


def dof_inverse_mass(sys: System, inv: InverseInertia, axes: torch.Tensor) -> torch.Tensor:
    """Inverse inertia ``(D, B)`` of each dof along its ``axes (3, D, B)`` through its two bodies:
    ``a^T (I_c^-1 + I_p^-1) a`` for a hinge, ``1/m_c + 1/m_p`` for a slide (whose force acts at the child's COM)."""
    child, parent = dof_bodies(sys)
    m_c, i_c = gather(inv, child)
    m_p, i_p = gather(inv, parent)
    w_hinge = spatial.dot(axes, spatial.matvec(i_c + i_p, axes))
    return torch.where(lanes.param(sys.dof_is_hinge, 1), w_hinge, m_c + m_p)


def dof_rate_change(sys: System, axes: torch.Tensor, before: Bodies, after: Bodies) -> torch.Tensor:
    """Change ``(D, B)`` of every dof's rate between two velocity states of the same poses."""
    child, parent = dof_bodies(sys)
    d_ang = after.xd_ang - before.xd_ang
    d_vel = after.xd_vel - before.xd_vel
    rel = torch.where(lanes.param(sys.dof_is_hinge, 1),
                      d_ang.index_select(-2, child) - d_ang.index_select(-2, parent),
                      d_vel.index_select(-2, child) - d_vel.index_select(-2, parent))
    return spatial.dot(axes, rel)


def apply_dof_impulse(sys: System, bodies: Bodies, inv: InverseInertia, axes: torch.Tensor, impulse: torch.Tensor,
                      position: bool) -> Bodies:
    """Apply equal and opposite impulses ``(D, B)`` along every dof's ``axes (3, D, B)`` (hinge: angular; slide:
    linear at the child's COM) to the velocities, or with ``position=True`` as an XPBD correction to the poses."""
    child, parent = dof_bodies(sys)
    p = impulse * axes
    hinge = lanes.param(sys.dof_is_hinge, 1)
    zero = torch.zeros_like(p)
    arm = bodies.x_pos.index_select(-2, child) - bodies.x_pos.index_select(-2, parent)
    apply = apply_pair_position if position else apply_pair_velocity
    return apply(bodies, inv, child, parent, zero, arm, torch.where(hinge, zero, p), torch.where(hinge, p, zero))


def dof_wrench(sys: System, bodies: Bodies, axes: torch.Tensor, tau: torch.Tensor):
    """Ext-indexed ``(force, torque)`` ``(3, N + 1, B)`` exerting generalized forces ``tau (D, B)`` along dof
    ``axes (3, D, B)``: a hinge torque turns child and parent against each other; a slide force pushes the child's
    COM and, equal and opposite at that same point, the parent."""
    child, parent = dof_bodies(sys)
    wrench = tau * axes
    hinge = lanes.param(sys.dof_is_hinge, 1)
    lin = torch.where(hinge, 0.0, wrench)
    ang = torch.where(hinge, wrench, 0.0)
    arm = bodies.x_pos.index_select(-2, child) - bodies.x_pos.index_select(-2, parent)
    zero = torch.zeros_like(bodies.x_pos)
    force = scatter_pair(zero, child, parent, lin, -lin)
    torque = scatter_pair(zero, child, parent, ang, -ang - spatial.cross(arm, lin))
    return force, torque
