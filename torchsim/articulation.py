"""The joint-space inertia of the bodies' kinematic tree, MuJoCo's mass matrix ``M``, built from the bodies' poses
in maximal coordinates.

Every dof moves the bodies below it in the tree: a hinge turns them about its axis through its joint's anchor, a
slide translates them along its axis, a ball joint turns them about its anchor and a free body moves and turns
its subtree about its own COM (three dofs each, world axes: the bodies' response to impulses along the other dofs
does not depend on the basis chosen for these). Body ``b``'s COM velocity and angular velocity are ``J_b qd``
(world frame), so ``M = sum_b J_b^T diag(m_b, I_b) J_b`` (plus the dofs' armature), and an impulse with generalized
components ``tau`` changes the rates by ``M^-1 tau`` and the bodies' velocities by ``J M^-1 tau``: the response of
the articulation with rigid joints, where the spring method's joints pass an impulse on only through their springs.

Columns (``C``): the System's hinge and slide dofs in its order (``D``), then three per ball joint, then six per
free body (linear, then angular). Hinges at offset anchors and general joints are refused. The tables are built at
load (:func:`tree_fields`); a System loaded without them gets them from :func:`with_tree`.
"""

from typing import NamedTuple

import numpy as np
import torch

from torchsim import lanes, spatial
from torchsim.kinematics import Bodies, JointFrames, dof_values
from torchsim.system import System


class Articulation(NamedTuple):
    """The joint-space inertia ``inertia (C, C, B)`` [kg, kg m, kg m^2] of the bodies at one pose (no armature:
    :func:`column_armature`), the Jacobians ``ang, vel (3, C, N, B)``: each body's angular velocity [rad/s] and COM
    velocity [m/s] per unit rate of each column, the columns themselves ``(3, C, B)``: each one's rotation axis
    ``axis_ang`` (zero for a slide), translation axis ``axis_lin`` (zero for a hinge) and the point ``pivot`` [m] it
    turns about (world), and the bodies' world inertias ``inertia_world (3, 3, N, B)`` [kg m^2] they were built
    from."""

    inertia: torch.Tensor
    ang: torch.Tensor
    vel: torch.Tensor
    axis_ang: torch.Tensor
    axis_lin: torch.Tensor
    pivot: torch.Tensor
    inertia_world: torch.Tensor


def tree_fields(jnt_child, jnt_parent, dof_flat, ball_joint, free_body, num_bodies: int, refusal: str | None) -> dict:
    """The System's load-time tables of the tree (``System.tree_*``): ``tree_moves (C, N)`` 1 where column ``c``'s
    joint is body ``n``'s or one of its ancestors', else 0; ``tree_lin, tree_ang (3, C)`` the unit columns of the
    ball joints' and free bodies' dofs (zero in the hinge and slide columns, whose axes move with the bodies).
    ``refusal``: why the model's joints cannot be columns (offset anchors, general joints), raised as ValueError."""
    if refusal:
        raise ValueError(f"articulation: {refusal}")
    child, parent = [int(c) for c in jnt_child], [int(p) for p in jnt_parent]
    joint_of, parent_of = {c: j for j, c in enumerate(child)}, dict(zip(child, parent))
    roots = [int(b) for b in free_body]
    column_joints = ([int(d) // 6 for d in dof_flat] + [int(j) for j in ball_joint for _ in range(3)]
                     + [("free", b) for b in roots for _ in range(6)])
    moves = np.zeros((len(column_joints), num_bodies))
    for body in range(num_bodies):
        movers, link = set(), body
        while link in joint_of:  # up to a body on the world or a free body
            movers.add(joint_of[link])
            link = parent_of[link]
        if link in roots:
            movers.add(("free", link))
        moves[:, body] = [column in movers for column in column_joints]
    eye, zero = np.eye(3), np.zeros((3, 3))
    hinges_slides = np.zeros((3, len(dof_flat)))
    balls = np.tile(eye, len(ball_joint))
    lin = np.concatenate((hinges_slides, 0.0 * balls, np.tile(np.concatenate((eye, zero), 1), len(roots))), 1)
    ang = np.concatenate((hinges_slides, balls, np.tile(np.concatenate((zero, eye), 1), len(roots))), 1)
    return dict(tree_moves=torch.as_tensor(moves), tree_lin=torch.as_tensor(lin), tree_ang=torch.as_tensor(ang))


def no_tree(num_bodies: int) -> dict:
    """:func:`tree_fields` without columns, for a System whose step does not read them."""
    return dict(tree_moves=torch.zeros(0, num_bodies), tree_lin=torch.zeros(3, 0), tree_ang=torch.zeros(3, 0))


def refusal(sys: System) -> str | None:
    """Why ``sys``'s joints cannot be the tree's columns, or None."""
    if sys.jnt_has_offsets or sys.jnt_has_general:
        return "hinges at offset anchors and general joints are not supported"
    return None


def with_tree(sys: System) -> System:
    """``sys`` with the tree's tables (:func:`tree_fields`), for a System loaded without them."""
    fields = tree_fields(sys.jnt_child, sys.jnt_parent, sys.dof_flat, sys.ball_joint, sys.free_body,
                         sys.num_bodies, refusal(sys))
    return sys.replace(**{name: value.to(device=sys.device, dtype=sys.dtype) for name, value in fields.items()})


def articulation(sys: System, bodies: Bodies, frames: JointFrames, rot: torch.Tensor) -> Articulation:
    """The :class:`Articulation` at the poses of ``bodies`` (lanes, ``B`` envs), with ``frames`` measured from
    them and ``rot (3, 3, N + 1, B)`` their rotation matrices (``rigid.InverseInertia.rot``)."""
    x_pos = bodies.x_pos[:, :-1]
    batch = x_pos.shape[-1]
    joint = sys.dof_flat // 6
    hinge = lanes.param(sys.dof_is_hinge, 1)
    axes = dof_axes(sys, frames)  # (3, D, B)
    anchor = x_pos.index_select(1, sys.jnt_child) + frames.r_child  # (3, J, B) world
    n_dof = axes.shape[1]
    fixed_lin, fixed_ang = sys.tree_lin[:, n_dof:, None], sys.tree_ang[:, n_dof:, None]  # (3, C - D, 1)
    ang = torch.cat((torch.where(hinge, axes, 0.0), fixed_ang.expand(-1, -1, batch)), 1)  # (3, C, B)
    lin = torch.cat((torch.where(hinge, 0.0, axes), fixed_lin.expand(-1, -1, batch)), 1)
    pivot = torch.cat((anchor.index_select(1, joint), anchor.index_select(1, sys.ball_joint.repeat_interleave(3)),
                       x_pos.index_select(1, sys.free_body.repeat_interleave(6))), 1)  # (3, C, B)
    moves = sys.tree_moves[:, :, None]  # (C, N, 1)
    ang_jac = ang[:, :, None] * moves  # (3, C, N, B)
    vel_jac = (lin[:, :, None] + spatial.cross(ang[:, :, None], x_pos[:, None] - pivot[:, :, None])) * moves
    body_rot = rot[..., :-1, :]
    inertia_world = spatial.mm(body_rot, lanes.param(sys.body_inertia, 1, 2), spatial.transpose(body_rot))
    mass = lanes.param(sys.body_mass, 1)  # (N, 1 | B)
    # sum over bodies of m v_c . v_d + w_c . I w_d, as broadcast products: (3, C, 1, N, B) x (3, 1, C, N, B)
    turned = spatial.matvec(inertia_world[:, :, None], ang_jac)  # (3, C, N, B): I_b w_c
    inertia = ((vel_jac * mass)[:, :, None] * vel_jac[:, None] + ang_jac[:, :, None] * turned[:, None]).sum((0, 3))
    return Articulation(inertia, ang_jac, vel_jac, ang, lin, pivot, inertia_world)


def dof_axes(sys: System, frames: JointFrames) -> torch.Tensor:
    """Each dof's world axis ``(3, D, B)`` at the poses ``frames`` measured: the direction a slide moves its child
    along, or the one a hinge turns it about, per unit rate (the Jacobian's columns). A joint of three hinges holds
    its dual rows in ``frames.axes`` (the directions its generalized forces act along); its columns are those of
    the rows' inverse."""
    axes = dof_values(sys, frames.axes)
    if not sys.jnt_kinds[3]:
        return axes
    joint, slot = sys.dof_flat // 6, (sys.dof_flat % 6 - 3).clamp_min(0)
    columns = spatial.inv3(frames.hinge_dual)[:, slot, joint]  # (3, D, B): column ``slot`` of each dof's joint
    three = (lanes.param(sys.jnt_mode, 2, 0)[joint, 3] > 0) & lanes.param(sys.dof_is_hinge, 1)  # (D, 1)
    return torch.where(three, columns, axes)


def velocity_product(sys: System, model: Articulation, bodies: Bodies, frames: JointFrames,
                     rates: torch.Tensor) -> Bodies:
    """The bodies' COM and angular accelerations ``(3, N + 1, B)`` (the world's zero) at zero joint acceleration,
    ``d/dt(J) qd``, for bodies moving as the tree with the columns' ``rates (C, B)``: the centripetal and Coriolis
    accelerations that the joints' constraint forces supply (MuJoCo's bias force is ``J^T`` of these, through the
    bodies' inertias, plus the gyroscopic torques). Every column's axes and pivot move with the bodies: a joint's
    slides and first hinge turn with its parent, a later hinge also with the hinges before it (MuJoCo composes a
    body's joints in order), at angular velocity ``w_c``; a ball's and a free body's world axes do not turn; each
    pivot moves at its point's velocity ``v_p`` on the joint's child. So ``d/dt`` of a column's ``(ang, vel)`` on
    body ``b`` is ``(w_c x a, w_c x l + (w_c x a) x (x_b - p) + a x (v_b - v_p))``."""
    n, n_dof = sys.num_bodies, sys.dof_flat.shape[0]
    joint, slot = sys.dof_flat // 6, sys.dof_flat % 6
    # the hinges before each hinge dof in its joint: (D, D) 1 where dof k turns dof c's axis
    before = (joint[:, None] == joint[None]) & (slot[None] >= 3) & (slot[None] < slot[:, None])
    turning = model.axis_ang[:, :n_dof] * rates[:n_dof]  # (3, D, B): each hinge's part of its child's rotation
    carrier = (bodies.xd_ang.index_select(1, sys.jnt_parent[joint])
               + (before.to(rates.dtype)[:, :, None] * turning[:, None]).sum(2))
    joint_child = torch.cat((sys.jnt_child[joint], sys.jnt_child[sys.ball_joint].repeat_interleave(3)))
    r_child = torch.cat((frames.r_child.index_select(1, joint),
                         frames.r_child.index_select(1, sys.ball_joint.repeat_interleave(3))), 1)  # (3, C - 6F, B)
    pivot_vel = (bodies.xd_vel.index_select(1, joint_child)
                 + spatial.cross(bodies.xd_ang.index_select(1, joint_child), r_child))
    pivot_vel = torch.cat((pivot_vel, bodies.xd_vel.index_select(1, sys.free_body.repeat_interleave(6))), 1)
    carrier = torch.cat((carrier, torch.zeros_like(pivot_vel[:, n_dof:])), 1)  # (3, C, B); world axes do not turn
    turn_ang = spatial.cross(carrier, model.axis_ang) * rates  # (3, C, B), each times its rate
    turn_lin = spatial.cross(carrier, model.axis_lin) * rates
    x_pos, xd_vel = bodies.x_pos[:, :n, None], bodies.xd_vel[:, :n, None]  # (3, N, 1, B)
    moves = sys.tree_moves.T[:, :, None]  # (N, C, 1)
    ang = (turn_ang[:, None] * moves).sum(2)
    lin = ((turn_lin[:, None] + spatial.cross(turn_ang[:, None], x_pos - model.pivot[:, None])
            + spatial.cross((model.axis_ang * rates)[:, None], xd_vel - pivot_vel[:, None])) * moves).sum(2)
    world = lin.new_zeros(3, 1, lin.shape[-1])
    return bodies._replace(xd_vel=torch.cat((lin, world), 1), xd_ang=torch.cat((ang, world), 1))


def per_column(dof: torch.Tensor, ball: torch.Tensor, free: torch.Tensor) -> torch.Tensor:
    """A value per column ``(C, 1 | B)`` from the dofs' ``(D, 1 | B)``, the ball joints' ``(nball, 1 | B)`` and the
    free joints' ``(nfree, 1 | B)`` (MJCF gives such a joint one value for all of its dofs)."""
    return torch.cat((dof, ball.repeat_interleave(3, 0), free.repeat_interleave(6, 0)))


def column_armature(sys: System) -> torch.Tensor:
    """Every column's armature ``(C, 1 | B)`` [kg m^2 | kg]: the rotors an impulse on the bodies also turns."""
    return per_column(lanes.param(sys.dof_armature, 1), lanes.param(sys.ball_armature, 1),
                      lanes.param(sys.free_armature, 1))


def column_damping(sys: System) -> torch.Tensor:
    """Every column's joint damping ``(C, 1 | B)`` [N m s | N s]. (A free joint's acts on its body's COM velocity,
    MuJoCo's on its frame's origin's: the same where the origin is at the COM.)"""
    return per_column(lanes.param(sys.dof_damping, 1), lanes.param(sys.ball_damping, 1),
                      lanes.param(sys.free_damping, 1))


def add_diagonal(matrix: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """``matrix (C, C, B)`` with ``values (C, 1 | B)`` added to its diagonal (e.g. :func:`column_armature`, which
    makes the joint-space inertia MuJoCo's ``M``)."""
    n_columns, batch = matrix.shape[0], matrix.shape[-1]
    diagonal = torch.arange(n_columns, device=matrix.device) * (n_columns + 1)
    return matrix.flatten(0, 1).index_add(0, diagonal, values.expand(-1, batch)).view(n_columns, n_columns, batch)


def move(bodies: Bodies, model: Articulation, rate_change: torch.Tensor) -> Bodies:
    """``bodies`` (lanes, world last) with each body's velocities changed by its Jacobian times the columns' rate
    change ``(C, B)``: the motion of the rigid tree."""
    world = bodies.xd_vel.new_zeros(3, 1, bodies.xd_vel.shape[-1])
    d_vel = torch.cat(((model.vel * rate_change[:, None]).sum(1), world), 1)
    d_ang = torch.cat(((model.ang * rate_change[:, None]).sum(1), world), 1)
    return bodies._replace(xd_vel=bodies.xd_vel + d_vel, xd_ang=bodies.xd_ang + d_ang)
