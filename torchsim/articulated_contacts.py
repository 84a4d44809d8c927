"""MuJoCo's soft contacts solved through the articulation (``load_mjcf(contact_model="articulated")``, the spring
method).

The soft contact normal (``torchsim.soft_contacts``) solves ``(A + R) p = target - v_free``, ``A`` the points'
inverse inertia. The soft model takes ``A`` through the touching bodies alone, and the rest of a robot follows
through its joint springs, a substep or more later: a hopper's foot landing stops the foot, and the leg and torso
above it swing on and stretch the springs. Here ``A = J_n M^-1 J_n^T``, ``M`` the tree's joint-space inertia with
armature (``torchsim.articulation``) and ``J_n`` the points' normal rows in its columns, as MuJoCo's constraint
solve has it, and the impulses move every body by its Jacobian times ``M^-1 J_c^T p``: the landing stops the leg
and torso with the foot, as rigid joints would. Passive rollouts of gymnasium's hopper and walker2d then miss MuJoCo
by 2.9x and 2.4x its own dt sensitivity, where the body-local soft contacts miss by 233x and 194x
(``docs/physics.md``).

Friction is solved with the normal, as MuJoCo's default pyramidal cone has it: each point pushes along four edges ``n +-
mu t`` (``soft_contacts.pyramid_edges``), every edge a row of one ``4K x 4K`` solve through the tree, each with its own
reference speed and MuJoCo's edge regulariser, the edges that would pull released by principal pivoting
(``soft_contacts.nonnegative_solve``). An elliptic cone's friction (``<option cone="elliptic">``) is solved on the same
pyramid. One env step from the states a trained Ant visits then misses MuJoCo's converged answer by less than MuJoCo at
its own time step does (``studies/transfer_step_error.py``; ``docs/transfer_gap.md``).

The cost is dense: ``C^2 N`` products to build ``M``, one ``C x C`` factorisation and ``4K`` solves with it, and
``PIVOT_PASSES`` factorisations of the ``4K x 4K`` edge system, per env and substep (``C`` columns, ``N`` bodies,
``K`` contact points).
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
    edges = soft_contacts.pyramid_edges(con)  # (4, 3, K, B)
    edge_rows = torch.cat(point_rows(model, bodies, con, edges.unbind(0)), 1)  # (C, 4K, B), edge-major
    mobility = spatial.spd_solve(articulation.with_armature(sys, model.inertia), edge_rows)  # M^-1 J^T
    inverse_inertia = (edge_rows.unsqueeze(2) * mobility.unsqueeze(1)).sum(0)  # (4K, 4K, B)
    v_rel, v_rel_start = (rigid.contact_arms(b, con.body_a, con.body_b, con.pos)[2] for b in (bodies, start))
    edge_impulses = soft_contacts.pyramid_impulses(sys, con, inverse_inertia, (edges * v_rel).sum(1),
                                                   (edges * v_rel_start).sum(1), h)  # (4, K, B)
    rate_change = (mobility * edge_impulses.flatten(0, 1)).sum(1)
    return con, (edge_impulses.unsqueeze(1) * edges).sum(0), model, rate_change


def contact_impulses(sys: System, bodies: Bodies, frames: JointFrames, rot: torch.Tensor, start: Bodies,
                     h: float) -> Bodies:
    """``bodies`` after the contact impulses of :func:`impulse_terms`, through the tree."""
    _, _, model, rate_change = impulse_terms(sys, bodies, frames, rot, start, h)
    return articulation.move(bodies, model, rate_change)
