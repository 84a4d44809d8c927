"""Spring method: joints as stiff damped springs (explicit forces), contacts as velocity impulses; joint limits are
MuJoCo's soft constraint, solved with armature and damping (``joint_space.limit_rows``, shared with XPBD).

Spring stiffness is set per joint from the effective mass it acts on and the substep, ``k = kappa m / h^2``
(``kappa = System.joint_stiffness``, a fraction of the explicit stability limit), so light links get soft
springs and heavy ones stiff springs, and the joint error scales as ``h^2``. The gains (and the inertias that size
contact impulses) come from the poses at the step's start and are held for its substeps (:class:`StepTerms`): a
sixth fewer element ops per substep on the ant (15,901 instead of 18,951), every accuracy check unchanged. The
gains are held in each joint's lighter body's frame, so that they turn with a spinning link (:func:`gain_frame`).
Contacts take Brax's impulse form: a normal impulse removing approaching velocity plus a Baumgarte term
``depth / (e timeconst)``, Coulomb-capped friction, impulses averaged over a body's active contacts.

With ``contact_model="articulated"`` the joints are no springs: the substep is MuJoCo's Euler step on the rigid tree
(:func:`tree_velocities`, ``torchsim.tree_solve``, then ``kinematics.onto_tree``), sharing this module's applied
forces.

Tensors are in the lanes layout (``torchsim.lanes``): ext-indexed body vectors ``(3, N + 1, B)``, dof quantities
``(D, B)``.
"""

from typing import NamedTuple

import torch

from torchsim import (hinge_anchors, integrator, joint_space, spatial, rigid, soft_contacts, tendon_paths, tree_solve,
                      welds)
from torchsim.actuators import body_wrench
from torchsim.collision import contacts
from torchsim.fluid import fluid_wrench
from torchsim.kinematics import Bodies, JointFrames, dof_angles, dof_values, dof_window, joint_frames, onto_tree
from torchsim.methods._method import Method
from torchsim.system import System


def _subspace_inverse(k: torch.Tensor, proj: torch.Tensor) -> torch.Tensor:
    """``(P K P)^+`` restricted to the subspace of projector ``P`` (identity added on its complement); matrices
    ``(3, 3, ...)``."""
    return spatial.mm(proj, spatial.inv3(spatial.mm(proj, k, proj) + (spatial.eye3(k, k.ndim - 2) - proj)), proj)


def _joint_gains(sys: System, k_lin: torch.Tensor, k_ang: torch.Tensor, fr: JointFrames) -> torch.Tensor:
    """``(P K P)^+`` of the translation and rotation blocks ``k_lin, k_ang (3, 3, J, B)`` in their constrained
    directions ``P``, stacked ``(3, 3, lin/ang, J, B)``.

    Where the model's static structure fixes ``P``, exact closed forms replace the projections (on the ant, ~5% of a
    compiled substep's time): without slides ``P_lin = I``, so the gain is ``K^-1``; with
    single hinges only, ``P_ang = I - a a^T`` for the hinge axis ``a``, and ``(P K P)^+ = K^-1 - (K^-1 a)(K^-1 a)^T
    / (a^T K^-1 a)`` (it annihilates ``a`` and inverts ``P K P`` on the plane normal to it).
    """
    lin = _subspace_inverse(k_lin, fr.lin_proj) if sys.jnt_has_slides else spatial.inv3(k_lin)
    if sys.jnt_kinds == (False, True, False, False, False):
        axis = fr.axes[:, :, 3]  # slot 3, the first hinge: the projector's axis a1 (zero frame, world)
        k_inv = spatial.inv3(k_ang)
        k_inv_axis = spatial.matvec(k_inv, axis)
        ang = k_inv - spatial.outer(k_inv_axis, k_inv_axis / spatial.dot(axis, k_inv_axis))
    else:
        ang = _subspace_inverse(k_ang, fr.ang_proj)
    return torch.stack((lin, ang), 2)


def joint_gain(sys: System, fr: JointFrames, inv: rigid.InverseInertia) -> torch.Tensor:
    """Every joint's gain matrix ``(3, 3, lin/ang, J, B)``: ``K^-1`` with ``K`` the joint's inverse-inertia block
    in its constrained directions (see :func:`joint_wrench`).

    Child and parent are stacked on an entity axis in front of the joints, e.g. ``r (3, child/parent, J, B)``, so
    that each step of the computation is one batched op.
    """
    ends = torch.cat((sys.jnt_child, sys.jnt_parent))
    m, i = rigid.gather(inv, ends)
    m, i = m.unflatten(-2, (2, -1)), i.unflatten(-2, (2, -1))  # (2, J, 1 | B), (3, 3, 2, J, B): child, parent
    r = torch.stack((fr.r_child, fr.r_parent), 1)
    if sys.jnt_has_offsets:  # an anchor turning with the first hinge adds to the lever (torchsim.hinge_anchors)
        lever = hinge_anchors.lever(r, fr.anchor_turn.unsqueeze(2))
        k_lin = m.sum(-3) * spatial.eye3(m, 2) + spatial.mm(lever, i, spatial.transpose(lever)).sum(-3)
    else:
        k_lin = m.sum(-3) * spatial.eye3(m, 2) - spatial.skew_sandwich(r, i).sum(-3)
    return _joint_gains(sys, k_lin, i.sum(-3), fr)


def gain_frame(sys: System, inv: rigid.InverseInertia) -> torch.Tensor:
    """The rotations ``(3, 3, 1, J, B)`` of the frames the joints' gains are held in: each joint's lighter body's
    (the larger inverse mass; the child beside the static world), whose inverse inertia dominates the gain.

    Held for a step, gains then turn with that body (:func:`joint_wrench`): a link spinning about its hinge (the
    reacher's shoulder, driven to 200 rad/s) keeps the gains its inertia needs. Held in the world frame, a thin
    link's gains went stale once it had turned ~0.2 rad within the step; its off-axis error then grew ~3x per
    substep and the env diverged in a step (the reacher at 40 rad/s). Held in the heavier body's frame they go
    stale as the light one turns against it (the pusher's 5 g wrist flex link, parent of a 0.18 kg roll link)."""
    child, parent = sys.jnt_child, sys.jnt_parent
    on_child = inv.mass.index_select(-2, child) >= inv.mass.index_select(-2, parent)  # (J, 1 | B)
    return torch.where(on_child, inv.rot.index_select(-2, child), inv.rot.index_select(-2, parent)).unsqueeze(2)


def held_gain(sys: System, gain: torch.Tensor, inv: rigid.InverseInertia) -> torch.Tensor:
    """World-frame gains ``gain (3, 3, lin/ang, J, B)`` in the frames of :func:`gain_frame`."""
    rot = gain_frame(sys, inv)
    return spatial.mm(spatial.transpose(rot), gain, rot)


def joint_wrench(sys: System, bodies: Bodies, fr: JointFrames, gain: torch.Tensor, h: float,
                 inv: rigid.InverseInertia):
    """Ext-indexed ``(force, torque)`` ``(3, N + 1, B)`` of every joint's anchor spring and alignment spring, for
    gain matrices ``gain (3, 3, lin/ang, J, B)`` held in the frames of :func:`gain_frame` (:func:`held_gain`) and
    the substep's inverse inertias ``inv`` (their rotations and masses).

    The springs and dampers are ``kappa / h^2 K^-1`` and ``zeta / h K^-1`` with ``K`` the joint's inverse-inertia
    block in its constrained directions: every direction is corrected by the same fraction per substep, so thin
    links (a capsule's small inertia about its axis) stay inside the explicit stability limit.
    """
    child, parent = sys.jnt_child, sys.jnt_parent
    r = torch.stack((fr.r_child, fr.r_parent), 1)
    correction = (sys.joint_stiffness / (h * h) * torch.stack((fr.lin_err, fr.ang_err), 1)
                  + sys.joint_damping / h * _joint_rates(sys, bodies, fr, r))
    rot = gain_frame(sys, inv)  # (3, 3, 1, J, B): broadcast over lin/ang
    correction = spatial.matvec(spatial.transpose(rot), correction)
    force, torque = (-spatial.matvec(rot, spatial.matvec(gain, correction))).unbind(1)
    if sys.jnt_has_offsets:
        torque = torque + hinge_anchors.turn_moment(fr.anchor_turn, force)
    moment = spatial.cross(r, force.unsqueeze(1)) + torque.unsqueeze(1)  # about each body's COM
    wrench = torch.cat((force.unsqueeze(1).expand_as(moment), moment))  # (6, child/parent, J, B)
    zero = bodies.x_pos.new_zeros((6,) + bodies.x_pos.shape[1:])
    total = rigid.scatter_pair(zero, child, parent, wrench[:, 0], -wrench[:, 1])
    return total[:3], total[3:]


def _joint_rates(sys: System, bodies: Bodies, fr: JointFrames, r: torch.Tensor) -> torch.Tensor:
    """Every joint's anchor and alignment error rates ``(3, lin/ang, J, B)``, child against parent, for the arms
    ``r (3, child/parent, J, B)`` from each end's COM to the anchor."""
    ends = torch.cat((sys.jnt_child, sys.jnt_parent))
    vel, ang = bodies.xd_vel.index_select(-2, ends), bodies.xd_ang.index_select(-2, ends)
    vel, ang = vel.unflatten(-2, (2, -1)), ang.unflatten(-2, (2, -1))
    twist = torch.stack((vel + spatial.cross(ang, r), ang), 1)  # (3, lin/ang, child/parent, J, B) at the anchor
    rate = twist[:, :, 0] - twist[:, :, 1]
    if sys.jnt_has_offsets:  # the parent anchor also moves as the first hinge turns (torchsim.hinge_anchors)
        turn_rate = hinge_anchors.turn_rate(fr.anchor_turn, ang[:, 0], ang[:, 1])
        rate = torch.stack((rate[:, 0] - turn_rate, rate[:, 1]), 1)
    return rate


def contact_impulses(sys: System, bodies: Bodies, inv: rigid.InverseInertia, rot: torch.Tensor | None = None,
                     start: Bodies | None = None, h: float | None = None) -> Bodies:
    """``bodies`` after the contact impulses of :func:`contact_impulse_terms`."""
    con, r_a, r_b, p_lin, scale_a, scale_b = contact_impulse_terms(sys, bodies, inv, rot, start, h)
    return rigid.apply_pair_velocity(bodies, inv, con.body_a, con.body_b, r_a, r_b, p_lin, torch.zeros_like(p_lin),
                                     scale_a, scale_b)


def contact_impulse_terms(sys: System, bodies: Bodies, inv: rigid.InverseInertia, rot: torch.Tensor | None = None,
                          start: Bodies | None = None, h: float | None = None):
    """Velocity impulses stopping approach and separating at ``depth / (e contact_timeconst)``, or with
    ``sys.contact_soft`` MuJoCo's soft normal (``torchsim.soft_contacts``, from the bodies at the substep's
    ``start`` over ``h``); Coulomb-capped friction. ``rot``: the bodies' rotation matrices, if at hand
    (``collision.contacts``).

    The separating speed is the peak speed of MuJoCo's critically damped soft contact (``solref`` time constant
    ``tau``) pushing out a body that starts ``depth`` deep: ``depth t / tau^2 exp(-t / tau)``, largest at
    ``t = tau``. With ``depth / tau`` (2.7x that) a sphere started 10 cm deep jumped 1.18 m where MuJoCo's rises
    0.11 m, and 14% of the ant's reset poses launched the torso above its 1 m termination height (MuJoCo: 5%).

    Per contact, vectors are ``(3, C, B)`` and scalars ``(C, B)``. Returns the contacts, the arms ``r_a, r_b``
    from the bodies' COMs, each point's impulse ``p_lin`` on body a (body b takes ``-p_lin``) and the shares
    ``scale_a, scale_b`` (a float or ``(C, B)``) each body takes of it."""
    con = contacts(sys, bodies, rot)
    a, b = con.body_a, con.body_b
    r_a, r_b, v_rel = rigid.contact_arms(bodies, a, b, con.pos)
    v_n = spatial.dot(v_rel, con.normal)
    active = (con.depth > 0).to(con.depth.dtype)
    scale_a, scale_b = rigid.active_count(a, b, active, bodies.x_pos.shape[-2])
    if sys.contact_soft:  # each point's own share: friction's cap is its own, its stopping impulse averaged
        v_n_start = spatial.dot(rigid.contact_arms(start, a, b, con.pos)[2], con.normal)
        j_n = soft_contacts.normal_impulses(sys, con, soft_contacts.delassus(sys, bodies, inv, con), v_n, v_n_start, h)
        stop_share = scale_a if b is None else torch.minimum(scale_a, scale_b)
        scale_a, scale_b = 1.0, 1.0
    else:
        w_n = rigid.pair_inverse_mass(inv, a, b, r_a, r_b, con.normal)
        j_n = active * torch.relu(-v_n + con.depth / (torch.e * sys.contact_timeconst)) / w_n
        stop_share = 1.0
    v_t = v_rel - v_n * con.normal
    speed_t = spatial.safe_norm(v_t)
    tangent = v_t / speed_t
    w_t = rigid.pair_inverse_mass(inv, a, b, r_a, r_b, tangent)
    j_t = torch.minimum(stop_share * speed_t / w_t, con.friction * j_n)
    return con, r_a, r_b, j_n * con.normal - j_t * tangent, scale_a, scale_b


def dof_force_wrench(sys: System, bodies: Bodies, fr: JointFrames, axes: torch.Tensor, q: torch.Tensor,
                     ctrl: torch.Tensor):
    """Ext-indexed ``(force, torque)`` ``(3, N + 1, B)`` of the dofs' generalized forces: actuators, passive springs
    and tendons (spatial ones pulling on their sites, ``actuators.body_wrench``), for dof ``axes (3, D, B)``,
    coordinates ``q (D, B)`` (``kinematics.dof_angles``) and ``ctrl (U, B)``. (Joint limits are soft constraints
    solved with armature and damping, ``joint_space.limit_rows``; spatial tendons' limits follow in ``substep``.)"""
    return body_wrench(sys, bodies, axes, q, dof_values(sys, fr.qd), ctrl)


class StepTerms(NamedTuple):
    """The spring gains and contact inertias of a step's substeps, built from the poses at the step's start and held
    for its substeps; the errors and rates they multiply are measured every substep. And the window in which the
    substeps read the dofs' coordinates, around their values at the step's start. ``J`` joints, ``D`` dofs.

    Attributes:
        inv_inertia_body: (3, 3, N, 1 | B) body-frame inverse inertias (the world-frame ones are rebuilt every
            substep: the joint-space solve diverged on the reacher and pusher when it used a step's old ones).
        loaded: world-frame inverse masses and inertias with each hinge's armature on its child, for contacts
            (``joint_space.armature_loaded_inertia``).
        joint_gain: (3, 3, lin/ang, J, B) joint spring gain matrices, each in its joint's lighter body's frame
            (:func:`held_gain`).
        window: (2, D, B) ``kinematics.dof_window``.
    """

    inv_inertia_body: torch.Tensor
    loaded: rigid.InverseInertia
    joint_gain: torch.Tensor
    window: torch.Tensor


def step_terms(sys: System, bodies: Bodies, q: torch.Tensor, h: float) -> StepTerms:
    """:class:`StepTerms` at the poses of lanes ``bodies`` and their coordinates ``q (nq, B)``."""
    inv_inertia_body = rigid.body_inverse_inertia(sys)
    inv = rigid.inverse_inertia(sys, bodies.x_quat, inv_inertia_body)
    fr = joint_frames(sys, bodies, rot=inv.rot)
    axes = dof_values(sys, fr.axes)
    return StepTerms(inv_inertia_body, joint_space.armature_loaded_inertia(sys, inv, axes),
                     held_gain(sys, joint_gain(sys, fr, inv), inv), dof_window(sys, q))


def substep(sys: System, bodies: Bodies, ctrl: torch.Tensor, terms: StepTerms, h: float) -> Bodies:
    """Forces (actuators, joint springs) -> velocities (armature, damping, limits) -> contact impulses (on
    armature-loaded links) -> positions; with articulated contacts, forces -> the rigid tree's velocity solve ->
    positions, put back onto the joints (:func:`tree_velocities`). Lanes ``bodies``, ``ctrl (U, B)``; ``terms``
    from :func:`step_terms` at the step's start."""
    if sys.contact_articulated:  # no joint springs: the tree's forward kinematics holds the joints exactly
        after = tree_velocities(sys, bodies, ctrl, terms, h)[0]
        return onto_tree(sys, integrator.integrate_positions(after, h), after, terms.window)
    after, inv, fr = free_velocities(sys, bodies, ctrl, terms, h)
    if sys.contact_groups:  # poses not yet moved: the substep's rot and joint frames
        after = contact_impulses(sys, after, terms.loaded, inv.rot, bodies, h)
    return integrator.integrate_positions(after, h)


def contact_forces(sys: System, bodies: Bodies, ctrl: torch.Tensor, terms: StepTerms, h: float):
    """The contacts of lanes ``bodies`` and the force ``(3, C, B)`` [N] each point's impulse puts on its body a over
    the first substep from them: what :func:`substep` applies, divided by ``h``."""
    if sys.contact_articulated:
        _, con, p_lin = tree_velocities(sys, bodies, ctrl, terms, h)
        return con, p_lin / h
    after, inv, fr = free_velocities(sys, bodies, ctrl, terms, h)
    con, _, _, p_lin, scale_a, _ = contact_impulse_terms(sys, after, terms.loaded, inv.rot, bodies, h)
    return con, scale_a * p_lin / h


def applied_forces(sys: System, bodies: Bodies, ctrl: torch.Tensor, terms: StepTerms, h: float,
                   springs: bool = True):
    """The substep's inverse inertias and joint frames at the poses of ``bodies``, the dofs' coordinates ``(D, B)``,
    and the ext-indexed ``(force, torque)`` ``(3, N + 1, B)`` on the bodies: actuators, passive springs, tendons,
    fluid, spatial tendons' limits and (``springs``) the joint springs."""
    inv = rigid.inverse_inertia(sys, bodies.x_quat, terms.inv_inertia_body)
    fr = joint_frames(sys, bodies, all_slots=False, rot=inv.rot)
    axes = dof_values(sys, fr.axes)
    q = dof_angles(sys, dof_values(sys, fr.q), terms.window)
    force, torque = dof_force_wrench(sys, bodies, fr, axes, q, ctrl)
    if springs:
        spring_force, spring_torque = joint_wrench(sys, bodies, fr, terms.joint_gain, h, inv)
        force, torque = force + spring_force, torque + spring_torque
    if sys.fluid:
        fluid_force, fluid_torque = fluid_wrench(sys, bodies, inv.rot)
        force, torque = force + fluid_force, torque + fluid_torque
    if sys.ten_path_limits:  # sized against every other force (tendon_paths.limit_wrench)
        limit_force, limit_torque = tendon_paths.limit_wrench(sys, bodies, inv, force, torque, axes,
                                                              dof_values(sys, fr.qd))
        force, torque = force + limit_force, torque + limit_torque
    return inv, fr, q, force, torque


def free_velocities(sys: System, bodies: Bodies, ctrl: torch.Tensor, terms: StepTerms, h: float):
    """The substep's velocities before contacts (forces, then armature, damping and limits), and the inverse
    inertias and joint frames at its poses."""
    inv, fr, q, force, torque = applied_forces(sys, bodies, ctrl, terms, h)
    after = integrator.velocity_update(sys, bodies, inv, force, torque, h)
    after, _ = joint_space.inertia_and_damping(sys, bodies, after, fr, inv, h, q)
    if sys.welds:  # on the armature-loaded links, as contacts: held by its rotor, a light link's hinge turns little
        after = welds.impulses(sys, bodies, after, terms.loaded, h)
    return after, inv, fr


def tree_velocities(sys: System, bodies: Bodies, ctrl: torch.Tensor, terms: StepTerms, h: float):
    """The articulated model's substep velocities, its contacts and each contact point's impulse ``(3, K, B)`` on
    its body a: the forces without the joint springs, the rigid tree's solve of armature, damping, limits and
    contacts (``torchsim.tree_solve``), welds."""
    inv, fr, q, force, torque = applied_forces(sys, bodies, ctrl, terms, h, springs=False)
    after, con, p_lin = tree_solve.solve(sys, bodies, force, torque, fr, inv.rot, q, h)
    if sys.welds:
        after = welds.impulses(sys, bodies, after, terms.loaded, h)
    return after, con, p_lin


METHOD = Method("spring", step_terms, substep, default_substep_timestep=5e-4, contact_forces=contact_forces)
