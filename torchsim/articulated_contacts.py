"""MuJoCo's soft contacts solved through the articulation (``load_mjcf(contact_model="articulated")``, the spring
method).

The soft contact normal (``torchsim.soft_contacts``) solves ``(A + R) p = target - v_free``, ``A`` the points'
inverse inertia. The soft model takes ``A`` through the touching bodies alone, and the rest of a robot follows
through its joint springs, a substep or more later: a hopper's foot landing stops the foot, and the leg and torso
above it swing on and stretch the springs. Here ``A = J_n M^-1 J_n^T``, ``M`` the tree's joint-space inertia with
armature (``torchsim.articulation``) and ``J_n`` the points' normal rows in its columns, as MuJoCo's constraint
solve has it, and the impulses move every body by its Jacobian times ``M^-1 J_c^T p``: the landing stops the leg
and torso with the foot, as rigid joints would. Passive rollouts of gymnasium's hopper and walker2d then miss MuJoCo
by 5.2x and 2.9x its own dt sensitivity, where the body-local soft contacts miss by 233x and 194x
(``docs/physics.md``).

Friction stays per point, as in the other contact models: a Coulomb-capped impulse stopping the point's sliding,
sized by the point's articulated inverse inertia along it and shared among its body's active points, applied with
the normals through the tree. The cost is dense: ``C^2 N`` products to build ``M``, one ``C x C`` factorisation and
``2K`` solves with it, and the ``K x K`` normal solve, per env and substep (``C`` columns, ``N`` bodies, ``K``
contact points).
"""

import torch

from torchsim import articulation, rigid, soft_contacts, spatial
from torchsim.collision import Contacts, contacts
from torchsim.kinematics import Bodies, JointFrames
from torchsim.system import System


def point_rows(model: articulation.Articulation, bodies: Bodies, con: Contacts, directions: tuple):
    """``(C, K, B)`` for each of ``directions`` ``(3, K, B)``: the rate along it of each contact point, body a's
    relative to body b's, per unit rate of each column. Each side's Jacobian is gathered once for all directions."""
    world = model.vel.new_zeros(model.vel.shape[:2] + (1,) + model.vel.shape[3:])
    vel_ext, ang_ext = torch.cat((model.vel, world), 2), torch.cat((model.ang, world), 2)
    rows = None
    for body, sign in ((con.body_a, 1.0), (con.body_b, -1.0)):
        if body is None:  # every pair a plane pair: b is the world
            continue
        vel, ang = vel_ext.index_select(2, body), ang_ext.index_select(2, body)  # (3, C, K, B)
        arm = con.pos - bodies.x_pos.index_select(-2, body)
        side = [sign * (spatial.dot(vel, d.unsqueeze(1)) + spatial.dot(ang, spatial.cross(arm, d).unsqueeze(1)))
                for d in directions]
        rows = side if rows is None else [r + s for r, s in zip(rows, side)]
    return rows


def impulse_terms(sys: System, bodies: Bodies, frames: JointFrames, rot: torch.Tensor, start: Bodies, h: float):
    """The contacts at the poses of lanes ``bodies`` (velocities after the substep's other forces), each point's
    impulse ``p_lin (3, K, B)`` on its body a, and the columns' rate change ``(C, B)`` the impulses make; ``frames``
    and ``rot (3, 3, N + 1, B)`` at those poses, ``start`` the bodies at the substep's start."""
    con = contacts(sys, bodies, rot)
    model = articulation.articulation(sys, bodies, frames, rot)
    a, b = con.body_a, con.body_b
    v_rel = rigid.contact_arms(bodies, a, b, con.pos)[2]
    v_n = spatial.dot(v_rel, con.normal)
    v_n_start = spatial.dot(rigid.contact_arms(start, a, b, con.pos)[2], con.normal)
    v_t = v_rel - v_n * con.normal
    speed_t = spatial.safe_norm(v_t)
    tangent = v_t / speed_t
    normal_rows, tangent_rows = point_rows(model, bodies, con, (con.normal, tangent))
    num_points = con.depth.shape[0]
    # M^-1 J^T for the normal and the tangent rows in one solve: (C, 2K, B)
    mobility = spatial.spd_solve(articulation.with_armature(sys, model.inertia),
                                 torch.cat((normal_rows, tangent_rows), 1))
    normal_mobility, tangent_mobility = mobility[:, :num_points], mobility[:, num_points:]
    inverse_inertia = (normal_rows.unsqueeze(2) * normal_mobility.unsqueeze(1)).sum(0)  # (K, K, B)
    j_n = soft_contacts.normal_impulses(sys, con, inverse_inertia, v_n, v_n_start, h)
    # a point on bodies no column moves (mocap against the world) meets no inverse inertia: it stops nothing
    w_t = (tangent_rows * tangent_mobility).sum(0).clamp_min(1e-12)
    active = (con.depth > 0).to(con.depth.dtype)
    share_a, share_b = rigid.active_count(a, b, active, bodies.x_pos.shape[-2])
    share = share_a if b is None else torch.minimum(share_a, share_b)
    j_t = torch.minimum(share * speed_t / w_t, con.friction * j_n)
    rate_change = (normal_mobility * j_n).sum(1) - (tangent_mobility * j_t).sum(1)
    return con, j_n * con.normal - j_t * tangent, model, rate_change


def contact_impulses(sys: System, bodies: Bodies, frames: JointFrames, rot: torch.Tensor, start: Bodies,
                     h: float) -> Bodies:
    """``bodies`` after the contact impulses of :func:`impulse_terms`, through the tree."""
    _, _, model, rate_change = impulse_terms(sys, bodies, frames, rot, start, h)
    return articulation.move(bodies, model, rate_change)
