"""Spring method: joints and limits as stiff damped springs (explicit forces), contacts as velocity impulses.

Spring stiffness is set per joint from the effective mass it acts on and the substep, ``k = kappa m / h^2``
(``kappa = System.joint_stiffness``, a fraction of the explicit stability limit), so light links get soft
springs and heavy ones stiff springs, and the joint error scales as ``h^2``. Contacts take Brax's impulse form:
a normal impulse removing approaching velocity plus a Baumgarte term ``erp * depth / h``, Coulomb-capped
friction, impulses averaged over a body's active contacts.
"""

import torch

from torchsim import integrator, joint_space, math, rigid
from torchsim.actuators import dof_forces
from torchsim.collision import contacts
from torchsim.kinematics import Bodies, JointFrames, dof_values, joint_frames
from torchsim.system import System


def _gains(sys: System, inv_mass: torch.Tensor, h: float):
    """Spring and damper coefficients for an effective inverse mass ``inv_mass``."""
    return sys.joint_stiffness / (h * h * inv_mass), sys.joint_damping / (h * inv_mass)


def joint_wrench(sys: System, bodies: Bodies, fr: JointFrames, inv: rigid.InverseInertia, h: float):
    """Ext-indexed ``(force, torque)`` of every joint's anchor spring and alignment spring."""
    child, parent = sys.jnt_child, sys.jnt_parent
    m_c, i_c = rigid.gather(inv, child)
    m_p, i_p = rigid.gather(inv, parent)
    s_c, s_p = math.skew(fr.r_child), math.skew(fr.r_parent)
    w_lin = (m_c + m_p)[..., 0] - torch.diagonal(s_c @ i_c @ s_c + s_p @ i_p @ s_p, dim1=-2, dim2=-1).sum(-1) / 3
    w_ang = torch.diagonal(i_c + i_p, dim1=-2, dim2=-1).sum(-1) / 3
    k_lin, c_lin = _gains(sys, w_lin[..., None], h)
    k_ang, c_ang = _gains(sys, w_ang[..., None], h)
    v_anchor = (bodies.xd_vel[:, child] + math.cross(bodies.xd_ang[:, child], fr.r_child)
                - bodies.xd_vel[:, parent] - math.cross(bodies.xd_ang[:, parent], fr.r_parent))
    w_rel = bodies.xd_ang[:, child] - bodies.xd_ang[:, parent]
    force = -k_lin * fr.lin_err - c_lin * math.matvec(fr.lin_proj, v_anchor)
    torque = -k_ang * fr.ang_err - c_ang * math.matvec(fr.ang_proj, w_rel)
    zero = torch.zeros_like(bodies.x_pos)
    return (rigid.scatter_pair(zero, child, parent, force, -force),
            rigid.scatter_pair(zero, child, parent, math.cross(fr.r_child, force) + torque,
                               -math.cross(fr.r_parent, force) - torque))


def limit_forces(sys: System, q: torch.Tensor, qd: torch.Tensor, w: torch.Tensor, h: float) -> torch.Tensor:
    """Generalized spring-damper force ``(B, D)`` on every dof outside its range (``w``: dof inverse inertia)."""
    lo, hi = sys.dof_range.unbind(-1)
    violation = torch.clamp(q - hi, min=0.0) + torch.clamp(q - lo, max=0.0)
    k, c = _gains(sys, w, h)
    return torch.where(sys.dof_limited & (violation != 0), -k * violation - c * qd, 0.0)


def contact_impulses(sys: System, bodies: Bodies, inv: rigid.InverseInertia, h: float) -> Bodies:
    """Velocity impulses stopping approach and removing ``contact_erp`` of the penetration per substep."""
    con = contacts(sys, bodies)
    a, b = con.body_a, con.body_b
    r_a = con.pos - bodies.x_pos[:, a]
    r_b = con.pos - bodies.x_pos[:, b]
    v_rel = (bodies.xd_vel[:, a] + math.cross(bodies.xd_ang[:, a], r_a)
             - bodies.xd_vel[:, b] - math.cross(bodies.xd_ang[:, b], r_b))
    v_n = math.dot(v_rel, con.normal)
    active = (con.depth > 0).to(con.depth.dtype)
    w_n = rigid.point_inverse_mass(inv, a, r_a, con.normal) + rigid.point_inverse_mass(inv, b, r_b, con.normal)
    j_n = active * torch.relu(-v_n[..., 0] + sys.contact_erp * con.depth / h) / w_n
    v_t = v_rel - v_n * con.normal
    speed_t = math.safe_norm(v_t)
    tangent = v_t / speed_t
    w_t = rigid.point_inverse_mass(inv, a, r_a, tangent) + rigid.point_inverse_mass(inv, b, r_b, tangent)
    j_t = torch.minimum(speed_t[..., 0] / w_t, con.friction * j_n)
    scale_a, scale_b = rigid.active_count(a, b, active, bodies.x_pos.shape[1])
    p_lin = j_n[..., None] * con.normal - j_t[..., None] * tangent
    return rigid.apply_pair_velocity(bodies, inv, a, b, r_a, r_b, p_lin, torch.zeros_like(p_lin),
                                     scale_a[..., None], scale_b[..., None])


def substep(sys: System, bodies: Bodies, ctrl: torch.Tensor, inv_inertia_body: torch.Tensor, h: float) -> Bodies:
    """Forces (actuators, limits, joint springs) -> velocities (armature, damping) -> contact impulses (with the
    armature's share) -> positions."""
    inv = rigid.inverse_inertia(sys, bodies.x_quat, inv_inertia_body)
    fr = joint_frames(sys, bodies)
    axes = dof_values(sys, fr.axes)
    q, qd = dof_values(sys, fr.q) + sys.dof_ref, dof_values(sys, fr.qd)
    tau = dof_forces(sys, q, qd, ctrl) + limit_forces(sys, q, qd, rigid.dof_inverse_mass(sys, inv, axes), h)
    force, torque = rigid.dof_wrench(sys, bodies, axes, tau)
    spring_force, spring_torque = joint_wrench(sys, bodies, fr, inv, h)
    after = integrator.velocity_update(sys, bodies, inv, inv_inertia_body, force + spring_force, torque + spring_torque, h)
    after, _ = joint_space.inertia_and_damping(sys, bodies, after, fr, inv, h)
    if sys.contact_groups:
        after = _contacts_with_armature(sys, after, fr, inv, h)
    return integrator.integrate_positions(after, h)


def _contacts_with_armature(sys: System, bodies: Bodies, fr: JointFrames, inv: rigid.InverseInertia, h: float):
    """Contact impulses, then the armature's share of their effect on the dofs."""
    touched = contact_impulses(sys, bodies, inv, h)
    slot_axes = fr.axes[..., 3:, :]
    ref = math.matvec(math.inv3(slot_axes.transpose(-1, -2)),
                      bodies.xd_ang[:, sys.jnt_child] - bodies.xd_ang[:, sys.jnt_parent])
    touched, _ = joint_space.hinge_rate_solve(sys, touched, inv, slot_axes, ref, torch.zeros_like(ref))
    if sys.jnt_has_slides:
        axes = dof_values(sys, fr.axes)
        deviation = torch.where(sys.dof_is_hinge, 0.0, rigid.dof_rate_change(sys, axes, bodies, touched))
        touched = rigid.apply_dof_impulse(sys, touched, inv, axes, joint_space.armature_impulse(sys, inv, axes, deviation),
                                          position=False)
    return touched
