"""The articulated model's velocity solve (``load_mjcf(contact_model="articulated")``): each substep's velocities
solved on the rigid tree, with armature, joint damping, soft limits and contacts in one system, as MuJoCo's
constraint solve has them; with its position update (``kinematics.onto_tree``) the substep is MuJoCo's Euler step.

The bodies move as the tree (``v = J qd``, ``torchsim.articulation``). The substep's forces (gravity, actuators,
passive springs, fluid), the gyroscopic torques and the velocity-product accelerations the joints supply
(``articulation.velocity_product``, MuJoCo's Coriolis and centripetal bias) give the columns' momenta after the
substep, ``tau = M qd + h (f - c)`` (:func:`column_impulse`), and the columns' rates solve ``(M + h D) qd' = tau +
J_c^T p``: ``M`` the joint-space inertia with armature, ``D`` the joint damping, implicit as in MuJoCo's Euler
integrator, ``p`` the constraints' impulses.
The bodies then move at ``v' = J qd'``, and the positions integrate in maximal coordinates and are put back onto the
joints by forward kinematics from the coordinates they read (each joint exact, no springs). Measured against MuJoCo
at the same timestep (one substep per timestep, the loader's default for this model): in the air the Ant's, the
Hopper's and a free chain's one-step errors are MuJoCo's own to three digits; the Hopper's 0.5 s landing stays
within 0.2 % of MuJoCo's own timestep sensitivity of MuJoCo's path (``tests/test_articulated_contacts.py``).
Bodies no column moves (welded to the world) end at rest; welds act on the bodies after this solve, and the
position update reads their effect onto the tree.

The constraints act on those rates as rows of the columns: every dof's soft limit (``joint_space.limit_rows``, a
unit row; the inactive ones held at 0) and every contact point's four pyramid edges (``articulated_contacts``),
solved together for impulses ``p >= 0`` through the rows' inverse inertia ``r M^-1 r^T`` on the rates the forces
and the damping force give, ``M^-1 (tau - h D qd)`` (``soft_contacts.nonnegative_solve``): a foot whose limit
carries the body under a contact load meets both in one system. Dry friction (``frictionloss``) then takes one
clamped Gauss-Seidel sweep. MuJoCo's order: its constraint solver sees ``M`` and the damping force explicitly, and
``mj_Euler`` makes the damping implicit only in the final solve (a limit stopping a hinge at 10 rad/s lands 0.1
rad/s apart if the constraints see ``M + h D`` instead, with the Ant's damping 1 and armature 1).

The cost is dense: ``C^2 N`` products to build ``M``, one ``C x C`` factorisation with ``1 + D + F + 4K`` right-hand
sides and one of ``M + h D`` with one, and ``PIVOT_PASSES`` factorisations of the ``(D + 4K)``-row constraint
system, per env and substep (``C`` columns, ``N`` bodies, ``D`` dofs, ``F`` frictional rows, ``K`` contact points).
"""

import torch

from torchsim import articulated_contacts, articulation, joint_space, lanes, rigid, soft_contacts, spatial
from torchsim.collision import Contacts, contacts
from torchsim.kinematics import Bodies, JointFrames, dof_values
from torchsim.system import System


def column_rates(sys: System, bodies: Bodies, frames: JointFrames) -> torch.Tensor:
    """The tree's columns' rates ``(C, B)`` at ``bodies`` (``frames`` measured from them): the dofs' rates, each
    ball joint's child's angular velocity relative to its parent's (world axes), each free body's COM velocity and
    angular velocity."""
    parts = [dof_values(sys, frames.qd)]
    if sys.ball_joint.shape[0]:
        child, parent = sys.jnt_child[sys.ball_joint], sys.jnt_parent[sys.ball_joint]
        relative = bodies.xd_ang.index_select(-2, child) - bodies.xd_ang.index_select(-2, parent)  # (3, nball, B)
        parts.append(relative.transpose(0, 1).flatten(0, 1))
    if sys.free_body.shape[0]:
        body = sys.free_body
        twist = torch.stack((bodies.xd_vel.index_select(-2, body), bodies.xd_ang.index_select(-2, body)))
        parts.append(twist.permute(2, 0, 1, 3).flatten(0, 2))  # (2, 3, nfree, B) -> (6 nfree, B)
    return torch.cat(parts)


def column_impulse(sys: System, model: articulation.Articulation, start: Bodies, frames: JointFrames,
                   rates: torch.Tensor, force: torch.Tensor, torque: torch.Tensor, h: float) -> torch.Tensor:
    """``(C, B)``: ``J^T`` of the bodies' momenta after a substep ``h`` of the forces ``force, torque (3, N + 1, B)``
    (world, at the COMs), gravity and the gyroscopic torques ``-w x I w``, less the momenta of their velocity-product
    accelerations (:func:`articulation.velocity_product`): MuJoCo's ``M qd + h (tau - c)`` for ``start``'s bodies
    (moving as the tree, at the columns' ``rates (C, B)``; ``model`` at their poses). Every term is
    explicit, as MuJoCo's bias force is (not the spring method's per-body implicit gyroscopic step, which each
    body would take through its own inertia alone).
    """
    n, inertia_world = sys.num_bodies, model.inertia_world
    mass = lanes.param(sys.body_mass, 1)
    bias = articulation.velocity_product(sys, model, start, frames, rates)
    w = start.xd_ang[:, :n]
    linear = (mass * (start.xd_vel[:, :n] + h * (lanes.param(sys.gravity, 0, 1)[:, None] - bias.xd_vel[:, :n]))
              + h * force[:, :n])
    angular = (spatial.matvec(inertia_world, w - h * bias.xd_ang[:, :n])
               + h * (torque[:, :n] - spatial.cross(w, spatial.matvec(inertia_world, w))))
    return (model.vel * linear[:, None]).sum((0, 2)) + (model.ang * angular[:, None]).sum((0, 2))


def ball_spring_impulse(sys: System, bodies: Bodies, frames: JointFrames, h: float) -> torch.Tensor:
    """The ball joints' springs' impulses over ``h`` on their columns ``(3 nball, B)``: ``-h K log(q_spring^-1 q)``
    (MuJoCo's ``mju_subQuat``, child frame) turned to world axes."""
    joint = sys.ball_joint
    offset = spatial.quat_mul(spatial.quat_conj(lanes.param(sys.ball_spring, 1, 1)),
                              frames.quat_rel.index_select(-2, joint))
    impulse = spatial.quat_rotate(bodies.x_quat.index_select(-2, sys.jnt_child[joint]),
                                  -h * lanes.param(sys.ball_stiffness, 1) * spatial.quat_to_rot_vec(offset))
    return impulse.transpose(0, 1).flatten(0, 1)


def solve(sys: System, start: Bodies, force: torch.Tensor, torque: torch.Tensor, frames: JointFrames,
          rot: torch.Tensor, q: torch.Tensor, h: float) -> tuple[Bodies, Contacts, torch.Tensor]:
    """The bodies after the solve, the contacts at their poses and each contact point's impulse ``p_lin (3, K, B)``
    on its body a. ``start``: the bodies at the substep's start, moving as the tree; ``force, torque (3, N + 1, B)``
    the substep's forces on them (world, at the COMs; gravity apart); ``frames`` and ``rot (3, 3, N + 1, B)`` at
    their poses; ``q (D, B)`` the dofs' coordinates (``kinematics.dof_angles``)."""
    model = articulation.articulation(sys, start, frames, rot)
    n_dof, n_columns, batch = sys.dof_flat.shape[0], model.inertia.shape[0], rot.shape[-1]
    rates = column_rates(sys, start, frames)
    armature = articulation.column_armature(sys)
    tau = column_impulse(sys, model, start, frames, rates, force, torque, h) + armature * rates
    if sys.ball_joint.shape[0]:
        tau = tau.index_add(0, torch.arange(n_dof, n_dof + 3 * sys.ball_joint.shape[0], device=tau.device),
                            ball_spring_impulse(sys, start, frames, h))
    inertia = articulation.add_diagonal(model.inertia, armature)  # M, with armature
    damping_h = h * articulation.column_damping(sys)

    con = contacts(sys, start, rot)
    edges = soft_contacts.pyramid_edges(con)  # (4, 3, K, B)
    edge_rows = torch.cat(articulated_contacts.point_rows(model, start, con, edges.unbind(0)), 1)  # (C, 4K, B)
    unit = torch.eye(n_columns, n_dof, dtype=tau.dtype, device=tau.device)[:, :, None]
    limits = joint_space.limit_rows(sys, q, rates[:n_dof], h) if sys.dof_limits else None
    limit_rows = unit * limits.sign if limits is not None else unit[:, :0].expand(-1, -1, batch)
    friction = joint_space.friction_columns(sys, n_columns).to(tau)  # (C, F)
    rows = torch.cat((limit_rows.expand(-1, -1, batch), edge_rows), 1)  # (C, R, B): the constraints' rows
    # as MuJoCo's Euler step: the constraints are solved on M with the damping force explicit, and the damping is
    # implicit only in the rates' final solve, (M + h D) qd' = tau + the constraints' impulses (mj_Euler)
    solved = spatial.spd_solve(inertia, torch.cat(((tau - damping_h * rates).unsqueeze(1), rows,
                                                   friction[:, :, None].expand(-1, -1, batch)), 1))
    qd_free, mobility, friction_mobility = solved[:, 0], solved[:, 1:1 + rows.shape[1]], solved[:, 1 + rows.shape[1]:]

    impulse = constraint_impulses(sys, con, edges, limits, rows, mobility, qd_free, start, h)
    momentum = tau + (rows * impulse.unsqueeze(0)).sum(1)
    if friction.shape[1]:
        qd_constrained = qd_free + (mobility * impulse.unsqueeze(0)).sum(1)
        momentum = momentum + (friction[:, :, None] * dry_friction(sys, friction, friction_mobility, qd_constrained,
                                                                    h).unsqueeze(0)).sum(1)
    qd = spatial.spd_solve(articulation.add_diagonal(inertia, damping_h), momentum.unsqueeze(1))[:, 0]
    zero = start._replace(xd_vel=torch.zeros_like(start.xd_vel), xd_ang=torch.zeros_like(start.xd_ang))
    edge_impulses = impulse[limit_rows.shape[1]:].view(4, edges.shape[2], batch)
    return articulation.move(zero, model, qd), con, (edge_impulses.unsqueeze(1) * edges).sum(0)


def constraint_impulses(sys: System, con: Contacts, edges: torch.Tensor, limits: joint_space.LimitRows | None,
                        rows: torch.Tensor, mobility: torch.Tensor, qd_free: torch.Tensor, start: Bodies,
                        h: float) -> torch.Tensor:
    """The impulses ``p (R, B)`` (``>= 0``) of the constraints' rows ``rows (C, R, B)`` (the ``D`` limits' then the
    ``4K`` pyramid ``edges (4, 3, K, B)``), ``mobility = M^-1 rows``, on the columns' rates ``qd_free (C,
    B)``; ``start``, the bodies at the substep's start, gives the contacts' reference speeds."""
    batch = qd_free.shape[-1]
    if not rows.shape[1]:  # nothing to solve (nothing limited, no contact pairs)
        return qd_free.new_zeros(0, batch)
    v_rel_start = rigid.contact_arms(start, con.body_a, con.body_b, con.pos)[2]
    target, reg, active = soft_contacts.pyramid_rows(sys, con, (edges * v_rel_start).sum(1), h)
    if limits is not None:
        n_dof = limits.sign.shape[0]
        target = torch.cat((limits.sign * limits.target, target))
        reg = torch.cat((limits.reg.expand(n_dof, batch), reg))
        active = torch.cat((limits.active.expand(n_dof, batch), active))
    rhs = target - (rows * qd_free.unsqueeze(1)).sum(0)
    inverse_inertia = (rows.unsqueeze(2) * mobility.unsqueeze(1)).sum(0)  # (R, R, B)
    # start from the rows whose own reference asks for a push: a sliding point's trailing edges drop out at once
    return soft_contacts.nonnegative_solve(inverse_inertia, reg, rhs, active, active & (rhs > 0),
                                           passes=soft_contacts.PIVOT_PASSES)


def dry_friction(sys: System, friction: torch.Tensor, mobility: torch.Tensor, qd: torch.Tensor,
                 h: float) -> torch.Tensor:
    """The dry-friction impulses ``(F, B)`` on rates ``qd (C, B)``: along each frictional row ``c_r`` (``friction
    (C, F)``, ``mobility = M^-1 c_r`` ``(C, F, B)``) an impulse stopping the row, clamped to ``h frictionloss``,
    one Gauss-Seidel sweep in row order (exact for one row, or for rows that do not couple)."""
    limit = joint_space.hinge_friction_limits(sys, h)  # (F, B)
    w = (friction[:, :, None, None] * mobility.unsqueeze(1)).sum(0)  # (F, F, B): c^T M^-1 c
    speed = (friction[:, :, None] * qd.unsqueeze(1)).sum(0)  # (F, B)
    p = []  # (1, B) slices: row graphs (torchsim.execution.kernel.rows) cannot read a (1,)-shaped constant
    for k in range(speed.shape[0]):
        row = slice(k, k + 1)
        stop = -(speed[row] + sum(w[row, j] * p[j] for j in range(k))) / w[row, k]
        p.append(torch.minimum(torch.maximum(stop, -limit[row]), limit[row]))
    return torch.cat(p)
