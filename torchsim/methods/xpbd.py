"""XPBD: after an unconstrained substep, project contacts and joints onto their constraints by position.

Each joint is solved exactly (to first order) as one 6x6 block system: 3 translation rows and 3 rotation rows in
the joint's hinge-slot coordinates (hard for constrained directions), eliminated with 3x3 Schur complements.
Joint limits are MuJoCo's soft constraint (``joint_space.limit_rows``, shared with the spring method) as compliant
rows of the same blocks (:func:`_slot_limits`). Joints of one colour share no body and run in parallel; contacts,
then colours, follow Gauss-Seidel (``xpbd_iterations`` passes). Contacts on the same body are averaged (Jacobi).
Contact friction is positional Coulomb friction: the substep's tangential slip is undone up to ``mu`` times the
normal correction.
Velocities are then the substep's displacement over ``h``; armature gets its share of the projection's effect at
velocity level (``joint_space``), which is first order in ``h``: with armature much heavier than the links it
drives (the ant), the projection's bare-inertia displacements dominate and the ant settles too low (see the tests).
Joint dry friction (``frictionloss``) acts with armature and damping on the predicted rates, as a torque on the
bodies; the projection then turns a link's linear momentum about its pivot into rotation the friction did not see,
so a held hinge creeps at about ``tau h / I_com`` (``tau`` the torque it holds, ``I_com`` the link's inertia about
its own COM): 2.6x MuJoCo's soft-friction creep for a pendulum at h = 0.5 ms (``tests/test_frictionloss.py``).
"""

from typing import NamedTuple

import torch

from torchsim import hinge_anchors, integrator, joint_space, lanes, spatial, rigid, tendon_paths, welds
from torchsim.actuators import body_wrench
from torchsim.collision import contacts
from torchsim.fluid import fluid_wrench
from torchsim.kinematics import Bodies, dof_angles, dof_values, dof_window, in_window, joint_frames
from torchsim.methods._method import Method
from torchsim.system import System


def _slot_limits(sys: System, colour: torch.Tensor, fr, limits: joint_space.LimitRows, goal: torch.Tensor,
                 impulse: torch.Tensor, window: torch.Tensor):
    """The soft-limit rows of a colour's hinge slots ``(3, K, B)``: where a limit pushes, the coordinate's lead over
    its ``goal`` (``q + h target``, :func:`substep`), MuJoCo's ``R``, the armature and the row's ``impulse`` so far
    (``(D, B)`` for all dofs); and each slot's dof ``(3 K,)``. ``window``: the step's (``kinematics.dof_window``).

    The row's compliance (:func:`project_joints`) is MuJoCo's ``R`` times ``1 + J W`` (``J`` the armature, ``W``
    the row's diagonal in the Schur complement, its inverse inertia with the anchor held): the rotor rides with the
    dof, so the row moves it by ``W_J / (W_J + R)`` of its lead, ``W_J = W / (1 + J W)`` its inverse inertia with
    the rotor, as MuJoCo's limit does (the rotor's own share: :func:`_rotor_rates`)."""
    slots = sys.jnt_slot_dof[colour][:, 3:]
    has_dof = lanes.param(slots >= 0, 1, 1)
    dof = slots.T.reshape(-1).clamp_min(0)
    q = fr.q[:, 3:].movedim(1, 0)
    window = window.index_select(1, dof).view(2, *q.shape[:2], -1)
    q = in_window(q, window, lanes.param(sys.dof_ref[slots.clamp_min(0)], 1, 1), has_dof)
    slot = [x.index_select(0, dof).view(q.shape[:2] + x.shape[1:]) for x in (*limits, goal, impulse)]
    active, sign, _, reg, goal, impulse = slot
    lead = q - goal
    active = has_dof & active & (sign * lead < 0)
    armature = lanes.param(sys.dof_armature, 1).index_select(0, dof).view(q.shape[:2] + (-1,))
    return active, lead, reg, armature, impulse, dof


def project_joints(sys: System, bodies: Bodies, inv: rigid.InverseInertia, limits: joint_space.LimitRows | None = None,
                   goal: torch.Tensor | None = None, impulse: torch.Tensor | None = None,
                   window: torch.Tensor | None = None):
    """Solve every joint colour by colour: anchors coincide, constrained axes align, pushing limits move their
    dofs towards their goals (:func:`_slot_limits`).

    Per joint, 3 translation rows and 3 rotation rows in the joint's hinge-slot coordinates (``G = A^-1`` maps a
    relative rotation onto the slots' axes ``A``) are solved together by 3x3 Schur complements. A rotation row is
    hard for a constrained direction, compliant (XPBD's compliance: MuJoCo's soft limit) for a dof whose limit
    pushes, and absent for a free dof. Bodies are lanes (``(3|4, N + 1, B)``); per joint of a colour, the rows are
    vectors ``(3, K, B)`` and the blocks matrices ``(3, 3, K, B)``. With ``limits``, also returns their rows'
    accumulated ``impulse`` ``(D, B)`` (passed in: from the substep's earlier passes, XPBD's ``lambda``, so that
    further passes converge to the compliant row rather than stiffen it); the limits read the hinge angles in the
    step's ``window`` (``kinematics.dof_window``).
    """
    for colour in sys.jnt_colors:
        child, parent = sys.jnt_child[colour], sys.jnt_parent[colour]
        fr = joint_frames(sys, bodies, colour)
        m_c, i_c = rigid.gather(inv, child)
        m_p, i_p = rigid.gather(inv, parent)
        r_c, r_p = fr.r_child, fr.r_parent
        eye = spatial.eye3(m_c, 2)
        if sys.jnt_has_offsets:  # an anchor turning with the first hinge adds to the levers (torchsim.hinge_anchors)
            l_c, l_p = (hinge_anchors.lever(r, fr.anchor_turn) for r in (r_c, r_p))
            k_ll = ((m_c + m_p) * eye + spatial.mm(l_c, i_c, spatial.transpose(l_c))
                    + spatial.mm(l_p, i_p, spatial.transpose(l_p)))
            k_la = spatial.mm(l_c, i_c) + spatial.mm(l_p, i_p)
        else:  # the levers are -[r]x
            k_ll = (m_c + m_p) * eye - spatial.skew_sandwich(r_c, i_c) - spatial.skew_sandwich(r_p, i_p)
            k_la = -(spatial.skew_mm(r_c, i_c) + spatial.skew_mm(r_p, i_p))
        k_aa = i_c + i_p

        # rotation rows in hinge-slot coordinates: the 3 hinge slots as a vector (3, K, B)
        mode = lanes.param(sys.jnt_mode[colour], 1, 1)
        hard = mode[:3].cumsum(0) > 0  # a weld's slots; slots k >= n of an n-hinge joint (n = 1, 2)
        g = fr.hinge_dual
        error = spatial.matvec(g, fr.ang_err)
        if limits is not None:
            pushing, lead, reg, armature, held, dof = _slot_limits(sys, colour, fr, limits, goal, impulse, window)
            error = torch.where(hard, error, lead)
            hard = hard | pushing
        mask = hard.to(error.dtype)  # the diagonal of the rotation rows' projector P_m
        gt = spatial.transpose(g)

        a, b = k_ll, spatial.mm(k_la, gt) * mask[None]  # no slides: every translation is constrained, P_l = I
        if sys.jnt_has_slides:  # identity on the free directions keeps the blocks invertible
            p_l = fr.lin_proj
            a, b = spatial.mm(p_l, k_ll, p_l) + (eye - p_l), spatial.mm(p_l, b)
        c = mask[:, None] * spatial.mm(g, k_aa, gt) * mask[None] + eye * (1.0 - mask)
        a_inv = spatial.inv3(a)
        bt_ainv = spatial.mm(spatial.transpose(b), a_inv)
        rhs_l, rhs_s = -fr.lin_err, -mask * error
        schur = c - spatial.mm(bt_ainv, b)
        if limits is not None:
            compliance = torch.where(pushing, reg * (1.0 + armature * (schur * eye).sum(1)), 0.0)
            schur = schur + eye * compliance[None]
            rhs_s = rhs_s - compliance * held
        mu = spatial.matvec(spatial.inv3(schur), rhs_s - spatial.matvec(bt_ainv, rhs_l))
        if limits is not None:
            impulse = impulse.index_add(0, dof, torch.where(pushing, mu, 0.0).reshape(-1, mu.shape[-1]))
        p_lin = spatial.matvec(a_inv, rhs_l - spatial.matvec(b, mu))
        p_ang = spatial.matvec(gt, mu)
        if sys.jnt_has_offsets:
            p_ang = p_ang + hinge_anchors.turn_moment(fr.anchor_turn, p_lin)
        bodies = rigid.apply_pair_position(bodies, inv, child, parent, fr.r_child, fr.r_parent, p_lin, p_ang)
    return bodies if limits is None else (bodies, impulse)


def _rotor_rates(sys: System, limits: joint_space.LimitRows, qd_free: torch.Tensor) -> torch.Tensor:
    """The hinge rotors' rates ``(D, B)`` after the limits: a limit that pushes takes its rotor from the rate
    ``qd_free`` to MuJoCo's ``imp target + (1 - imp) qd_free`` (``A0 / (A0 + R) = imp``, :func:`joint_space.limit_rows`),
    the rate its row moves the link at (:func:`_slot_limits`) when the other joints hold still.

    Not the row's own move: Gauss-Seidel lets the next colours turn the link's neighbours back (a light thigh
    between the hip's and the knee's rows), the row pushes again in the next pass, and a heavy rotor riding with
    every push would gain the ping-pong as speed (the ant's ankles spun up to 1800 rad/s in one step)."""
    a0 = lanes.param(sys.dof_invweight, 1)
    push = limits.active & (limits.sign * (limits.target - qd_free) > 0)
    return torch.where(push, qd_free + a0 / (a0 + limits.reg) * (limits.target - qd_free), qd_free)


def correct_slides(sys: System, bodies: Bodies, inv: rigid.InverseInertia, q_pred: torch.Tensor,
                   limits: joint_space.LimitRows | None = None, goal: torch.Tensor | None = None) -> Bodies:
    """Slide dofs: give armature its share of the projection's effect (see ``joint_space.armature_impulse``; hinge
    dofs get theirs in ``substep``'s last rate solve), then move a dof whose limit pushes ``W_J / (W_J + R)`` of
    its lead over its ``goal`` (as :func:`_slot_limits`). ``q_pred (D, B)``: the dofs' coordinates predicted from
    their rates."""
    fr = joint_frames(sys, bodies)
    axes = dof_values(sys, fr.axes)
    q = dof_values(sys, fr.q) + lanes.param(sys.dof_ref, 1)
    slide = ~lanes.param(sys.dof_is_hinge, 1)
    impulse = torch.where(slide, joint_space.armature_impulse(sys, inv, axes, q - q_pred), 0.0)
    if limits is not None:
        w = rigid.dof_inverse_mass(sys, inv, axes)
        lead = q + w * impulse - goal
        w_rotor = w / (1.0 + lanes.param(sys.dof_armature, 1) * w)
        pushing = slide & limits.active & (limits.sign * lead < 0)
        impulse = impulse - torch.where(pushing, w_rotor / (w_rotor + limits.reg) * lead / w, 0.0)
    return rigid.apply_dof_impulse(sys, bodies, inv, axes, impulse, position=True)


def project_contacts(sys: System, bodies: Bodies, previous: Bodies, inv: rigid.InverseInertia):
    """Resolve penetration along the normal, then undo tangential slip within the Coulomb cone.

    Returns the corrected bodies, the contacts, and for the velocity pass their activity and averaging weights,
    ``(C, B)`` each.
    """
    con = contacts(sys, bodies)
    a, b = con.body_a, con.body_b
    r_a = con.pos - bodies.x_pos.index_select(-2, a)
    r_b = None if b is None else con.pos - bodies.x_pos.index_select(-2, b)
    active = (con.depth > 0).to(con.depth.dtype)
    scale_a, scale_b = rigid.active_count(a, b, active, bodies.x_pos.shape[-2])
    w_n = rigid.pair_inverse_mass(inv, a, b, r_a, r_b, con.normal)
    lam_n = active * con.depth / w_n

    def previous_point(idx, r):
        """Where the contact point, carried by body ``idx``, was at the start of the substep."""
        local = spatial.quat_rotate_inv(bodies.x_quat.index_select(-2, idx), r)
        return previous.x_pos.index_select(-2, idx) + spatial.quat_rotate(previous.x_quat.index_select(-2, idx), local)

    prev_a = previous_point(a, r_a)
    prev_b = con.pos if b is None else previous_point(b, r_b)  # a point on the static world stays put
    slip = prev_b - prev_a  # (p - prev_a) - (p - prev_b)
    slip = slip - spatial.dot(slip, con.normal) * con.normal
    slip_len = spatial.safe_norm(slip)
    tangent = slip / slip_len
    w_t = rigid.pair_inverse_mass(inv, a, b, r_a, r_b, tangent)
    lam_t = torch.minimum(slip_len / w_t, con.friction * lam_n)
    p_lin = lam_n * con.normal - lam_t * tangent
    bodies = rigid.apply_pair_position(bodies, inv, a, b, r_a, r_b, p_lin, torch.zeros_like(p_lin), scale_a, scale_b)
    return bodies, con, active, scale_a, scale_b


def stop_contacts(bodies: Bodies, inv: rigid.InverseInertia, con, active, scale_a, scale_b) -> Bodies:
    """Velocity pass: active contacts end the substep with zero normal velocity (inelastic, MuJoCo has no
    restitution); without it, depenetration would turn into a launch speed ``depth / h``. ``active``,
    ``scale_a``, ``scale_b``: ``(C, B)`` from :func:`project_contacts`."""
    a, b = con.body_a, con.body_b
    r_a, r_b, v_rel = rigid.contact_arms(bodies, a, b, con.pos)
    w_n = rigid.pair_inverse_mass(inv, a, b, r_a, r_b, con.normal)
    p_lin = -active * spatial.dot(v_rel, con.normal) / w_n * con.normal
    return rigid.apply_pair_velocity(bodies, inv, a, b, r_a, r_b, p_lin, torch.zeros_like(p_lin), scale_a, scale_b)


class StepTerms(NamedTuple):
    """What the substeps of a step share.

    Attributes:
        inv_inertia_body: (3, 3, N, 1 | B) body-frame inverse inertias (the world-frame ones are rebuilt at every
            projection's poses).
        window: (2, D, B) where the substeps read the dofs' coordinates (``kinematics.dof_window``).
    """

    inv_inertia_body: torch.Tensor
    window: torch.Tensor


def step_terms(sys: System, bodies: Bodies, q: torch.Tensor, h: float) -> StepTerms:
    """:class:`StepTerms` of a step starting at coordinates ``q (nq, B)``."""
    return StepTerms(rigid.body_inverse_inertia(sys), dof_window(sys, q))


def substep(sys: System, bodies: Bodies, ctrl: torch.Tensor, terms: StepTerms, h: float) -> Bodies:
    """Forces -> velocities -> positions; project contacts, then joints (with limits and armature); velocities
    from the displacement; inelastic contact velocity pass. All lanes: ext ``bodies``, ``ctrl (U, B)``; ``terms``
    from :func:`step_terms`."""
    inv_inertia_body = terms.inv_inertia_body
    inv = rigid.inverse_inertia(sys, bodies.x_quat, inv_inertia_body)
    fr = joint_frames(sys, bodies, all_slots=False, rot=inv.rot)
    axes = dof_values(sys, fr.axes)
    q, qd = dof_angles(sys, dof_values(sys, fr.q), terms.window), dof_values(sys, fr.qd)
    force, torque = body_wrench(sys, bodies, axes, q, qd, ctrl)
    if sys.fluid:
        fluid_force, fluid_torque = fluid_wrench(sys, bodies, inv.rot)
        force, torque = force + fluid_force, torque + fluid_torque
    if sys.ten_path_limits:
        limit_force, limit_torque = tendon_paths.limit_wrench(sys, bodies, inv, force, torque, axes, qd)
        force, torque = force + limit_force, torque + limit_torque
    after = integrator.velocity_update(sys, bodies, inv, force, torque, h)
    after, qd_pred = joint_space.inertia_and_damping(sys, bodies, after, fr, inv, h)
    if sys.welds:
        after = welds.impulses(sys, bodies, after, inv, h)
    q_pred = q + h * qd_pred
    moved = integrator.integrate_positions(after, h)
    inv = rigid.inverse_inertia(sys, moved.x_quat, inv_inertia_body)
    limits = joint_space.limit_rows(sys, q, qd, h) if sys.dof_limits else None
    goal = None if limits is None else q + h * limits.target  # where each limit's reference rate takes its dof
    impulse = None if limits is None else torch.zeros_like(goal)
    for _ in range(sys.xpbd_iterations):
        moved, con, active, scale_a, scale_b = project_contacts(sys, moved, bodies, inv)
        if limits is None:
            moved = project_joints(sys, moved, inv)
        else:
            moved, impulse = project_joints(sys, moved, inv, limits, goal, impulse, terms.window)
    if sys.jnt_has_slides:
        moved = correct_slides(sys, moved, inv, q_pred, limits, goal)
    xd_vel = (moved.x_pos - bodies.x_pos) / h
    xd_ang = spatial.quat_to_rot_vec(spatial.quat_mul(moved.x_quat, spatial.quat_conj(bodies.x_quat))) / h
    moved = stop_contacts(moved._replace(xd_vel=xd_vel, xd_ang=xd_ang), inv, con, active, scale_a, scale_b)
    rotor_ref = qd_pred if limits is None else _rotor_rates(sys, limits, qd_pred)
    moved, _ = joint_space.hinge_rate_solve(sys, moved, inv, fr, rotor_ref, torch.zeros_like(qd_pred))
    return moved


METHOD = Method("xpbd", step_terms, substep, default_substep_timestep=5e-4)
