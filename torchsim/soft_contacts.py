"""MuJoCo's soft contact normal, solved jointly for the contact points that share a body (the spring method with
``load_mjcf(contact_model="soft")``).

MuJoCo's contact forces solve ``(A + R) f = aref - a0`` over the active contacts: ``A`` their inverse inertia
through the bodies (coupled where points share a body), ``R = (1 - imp) / imp A0`` its regulariser, ``aref = -B v
+ K imp depth`` the reference acceleration of each point's ``solref``/``solimp`` and ``a0`` the acceleration of
every other force. Over a substep ``h`` that is the impulse ``p`` of ``(A + R) p = target - v_free``, ``target = v
+ h aref`` (``v`` the normal speed at the substep's start, ``v_free`` after the other forces).

Why jointly: at rest ``A p`` cancels ``a0``, so each point holds ``p_i = h aref_i / R_i``, a spring of its own, and
a box on four corners sinks a quarter as deep as on one. Impulses sized for each point alone and averaged over a
body's points (the impulse contact model) hold the box with one point's impulse: it sank 100x deeper than
MuJoCo's. The points couple through the bodies they share, not through joints (springs in this method). A point
that would pull (``p < 0``) is released after the solve: one pass, not MuJoCo's full complementarity.

MuJoCo's default pyramidal friction cone carries the normal force on 4 edges ``J_n +- mu J_t`` (condim 3), each
with ``R`` scaled by ``2 mu^2 (1 + mu^2)``: the normal is regularised by ``mu^2 (1 + mu^2) / 2`` times the bare
``R``, so a contact with friction 2 rests 5.3x deeper than with friction 1 (measured in MuJoCo; both reproduced,
``tests/test_soft_contacts.py``). A frictionless contact (condim 1) keeps the bare ``R``, as does an elliptic cone.
"""

import torch

from torchsim import lanes, rigid, spatial
from torchsim.collision import Contacts
from torchsim.kinematics import Bodies
from torchsim.system import System
from torchsim.tendons import impedance


def delassus(sys: System, bodies: Bodies, inv: rigid.InverseInertia, con: Contacts) -> torch.Tensor:
    """``A (C, C, B)``: the contact normals' inverse inertia through the moving bodies, ``J M^-1 J^T`` with ``J``
    the points' normal rows; built from the load-time incidences (``System.contact_inc_*``), so only pairs of
    points on a common body cost a product."""
    point, body = sys.contact_inc_point, sys.contact_inc_body
    num_points, batch = con.depth.shape
    normal = con.normal.index_select(-2, point) * lanes.param(sys.contact_inc_sign, 1)  # (3, P, B)
    arm = con.pos.index_select(-2, point) - bodies.x_pos.index_select(-2, body)
    moment = spatial.cross(arm, normal)
    inv_mass, inv_inertia = rigid.gather(inv, body)
    turn = spatial.matvec(inv_inertia, moment)
    first, second = sys.contact_inc_pairs.unbind(1)
    normal_first, moment_first = normal.index_select(-2, first), moment.index_select(-2, first)
    blocks = (inv_mass.index_select(-2, first) * spatial.dot(normal_first, normal.index_select(-2, second))
              + spatial.dot(moment_first, turn.index_select(-2, second)))  # (Q, B)
    flat = con.depth.new_zeros(num_points * num_points, batch)
    return flat.index_add(0, point[first] * num_points + point[second], blocks).view(num_points, num_points, batch)


def normal_impulses(sys: System, con: Contacts, inverse_inertia: torch.Tensor, v_n: torch.Tensor,
                    v_n_start: torch.Tensor, h: float) -> torch.Tensor:
    """Each point's normal impulse ``(C, B)`` (>= 0, 0 where inactive) for normal speeds ``v_n`` after the other
    forces and ``v_n_start`` at the substep's start ``(C, B)``, over a substep ``h``; ``inverse_inertia (C, C, B)``
    the normals' ``A``: through the bodies (:func:`delassus`, from armature-loaded inertias,
    ``joint_space.armature_loaded_inertia``) or through the articulation (``torchsim.articulated_contacts``)."""
    k, b = lanes.param(sys.contact_gains, 2).unbind(-2)
    imp = impedance(sys.contact_solimp, con.depth, sys.contact_solimp_square)
    target = v_n_start + h * (k * imp * con.depth - b * v_n_start)
    reg = (1.0 - imp) / imp * lanes.param(sys.contact_invweight, 1)
    if sys.contact_pyramidal:  # 4 edges J_n +- mu J_t share the normal, each regularised 2 mu^2 (1 + mu^2) R
        mu2 = con.friction * con.friction
        reg = reg * torch.where(mu2 > 0, 0.5 * mu2 * (1.0 + mu2), 1.0)
    active = con.depth > 0
    num_points = active.shape[0]
    # inactive points get an identity row and a zero right-hand side: impulse 0, no coupling
    both = (active.unsqueeze(1) & active.unsqueeze(0)).flatten(0, 1)
    flat = torch.where(both, inverse_inertia.flatten(0, 1), 0.0)
    diagonal = torch.arange(num_points, device=active.device) * (num_points + 1)
    mat = flat.index_add(0, diagonal, torch.where(active, reg, 1.0)).view(num_points, num_points, -1)
    impulse = spatial.spd_solve(mat, torch.where(active, target - v_n, 0.0))
    return torch.where(active, impulse.clamp_min(0.0), 0.0)
