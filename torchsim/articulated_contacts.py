"""The contact points' rows in the articulation's columns, for the articulated model's solve
(``load_mjcf(contact_model="articulated")``, ``torchsim.tree_solve``).

MuJoCo's constraint solve takes a contact through the whole tree: its inverse inertia is ``J_n M^-1 J_n^T``, ``M``
the tree's joint-space inertia with armature (``torchsim.articulation``) and ``J_n`` the point's normal row in its
columns, and an impulse moves every body by its Jacobian times ``M^-1 J^T p``: a hopper's foot landing stops the
leg and torso with the foot, as rigid joints would. (The soft model takes ``A`` through the touching bodies alone;
the rest of the robot follows through its joint springs a substep or more later, and passive rollouts of
gymnasium's hopper and walker2d miss MuJoCo by 233x and 194x its own dt sensitivity, ``docs/physics.md``.)

Friction is solved with the normal, as MuJoCo's default pyramidal cone has it: each point pushes along four edges ``n
+- mu t`` (``soft_contacts.pyramid_edges``), every edge a row with its own reference speed and MuJoCo's edge
regulariser (``soft_contacts.pyramid_rows``). An elliptic cone's friction (``<option cone="elliptic">``) is solved on
the same pyramid.
"""

import torch

from torchsim import articulation, spatial
from torchsim.collision import Contacts
from torchsim.kinematics import Bodies


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
