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

The articulated model (``torchsim.tree_solve``) solves those edges themselves, as MuJoCo does: each edge
a row with its own reference speed, the edges that would pull released by principal pivoting
(:func:`pyramid_rows`, :func:`nonnegative_solve`).
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
    the normals' ``A`` through the bodies (:func:`delassus`, from armature-loaded inertias,
    ``joint_space.armature_loaded_inertia``). One pass: a point that would pull is released after the solve."""
    target, reg = reference(sys, con, v_n_start, h)
    if sys.contact_pyramidal:  # 4 edges J_n +- mu J_t share the normal, each regularised 2 mu^2 (1 + mu^2) R
        mu2 = con.friction * con.friction
        reg = reg * torch.where(mu2 > 0, 0.5 * mu2 * (1.0 + mu2), 1.0)
    active = con.depth > 0
    return nonnegative_solve(inverse_inertia, reg, target - v_n, active, active, passes=1)


def pyramid_edges(con: Contacts) -> torch.Tensor:
    """``(4, 3, C, B)``: the directions ``n + mu t1, n - mu t1, n + mu t2, n - mu t2`` of MuJoCo's pyramidal cone
    (condim 3) at each point, ``t1, t2`` the tangents of MuJoCo's contact frame (``mju_makeFrame``: the point's
    ``con.tangent`` made normal to ``n`` where it is set, else world y, or world z where ``n`` is within 60 degrees
    of y; ``t2 = n x t1``). Frictionless points get four copies of the normal."""
    n = con.normal
    near_y = (n[1].abs() >= 0.5).to(n.dtype)
    seed = torch.stack((torch.zeros_like(near_y), 1.0 - near_y, near_y))
    hint = con.tangent - n * spatial.dot(n, con.tangent)
    # a hint along the normal (a capsule standing upright on the plane) leaves no tangent: MuJoCo then takes world x,
    # whose pyramid on a level floor is the default's turned by 90 degrees, the same four edges
    usable = (spatial.dot(con.tangent, con.tangent) >= 0.25) & (spatial.dot(hint, hint) > 1e-12)
    t1 = torch.where(usable, hint, seed - n * spatial.dot(n, seed))
    t1 = t1 / spatial.safe_norm(t1)
    t2 = spatial.cross(n, t1)
    mu = con.friction
    return torch.stack((n + mu * t1, n - mu * t1, n + mu * t2, n - mu * t2))


def pyramid_rows(sys: System, con: Contacts, v_e_start: torch.Tensor, h: float):
    """The rows of MuJoCo's pyramidal cone (:func:`pyramid_edges`) for a constraint solve, edge-major ``(4C, B)``
    each: the speed each edge aims for over the substep (its reference, built from its point's depth and the edge's
    own speed ``v_e_start (4, C, B)`` at the substep's start), its regulariser ``2 mu^2 (1 + mu^2) R`` (``4 R``: a
    frictionless point's four copies of its normal act as one with ``R``) and whether its point touches. An
    elliptic cone's friction is solved on the same pyramid, its normal with the bare ``R`` (``4 R`` on each edge),
    as MuJoCo regularises an elliptic cone's normal."""
    target, reg = reference(sys, con, v_e_start, h)
    if sys.contact_pyramidal:
        mu2 = con.friction * con.friction
        reg = reg * torch.where(mu2 > 0, 2.0 * mu2 * (1.0 + mu2), 4.0)
    else:
        reg = 4.0 * reg
    active = (con.depth > 0).expand_as(v_e_start)
    return target.flatten(0, 1), reg.expand_as(v_e_start).flatten(0, 1), active.flatten(0, 1)


def reference(sys: System, con: Contacts, v_start: torch.Tensor, h: float):
    """The speed ``target = v + h aref`` each row aims for over the substep, for speeds ``v_start (..., C, B)`` at
    its start along the rows, and each point's bare regulariser ``R = (1 - imp) / imp A0`` ``(C, B)``."""
    k, b = lanes.param(sys.contact_gains, 2).unbind(-2)
    imp = impedance(sys.contact_solimp, con.depth, sys.contact_solimp_square)
    target = v_start + h * (k * imp * con.depth - b * v_start)
    return target, (1.0 - imp) / imp * lanes.param(sys.contact_invweight, 1)


# Principal pivoting passes of the pyramid solve. On the states a trained Ant visits (studies/transfer_step_error.py)
# the share of envs whose set still changes after each pass is 21 %, 5 %, 0.8 %, 0.09 %, and the step's error
# against MuJoCo is the same with 4 passes as with 8.
PIVOT_PASSES = 4


def nonnegative_solve(inverse_inertia: torch.Tensor, reg: torch.Tensor, rhs: torch.Tensor, active: torch.Tensor,
                      start: torch.Tensor, passes: int) -> torch.Tensor:
    """``p (R, B)``, ``p >= 0``, minimising ``p^T (A + R) p / 2 - rhs^T p`` over the ``active`` rows (the rest held
    at 0), for ``A = inverse_inertia (R, R, B)`` and ``R = diag(reg (R, B))``: the complementarity of a contact
    solve (``(A + R) p - rhs`` is 0 where ``p > 0`` and ``>= 0`` where ``p = 0``) by block principal pivoting with a
    fixed number of passes, branch-free. Each pass solves for the rows in its set (the first: ``start``) and then
    drops the rows that pull (``p < 0``) and takes back those the solution would push through (residual ``< 0``);
    after the last, pulling rows are released."""
    num_rows = active.shape[0]
    diagonal = torch.arange(num_rows, device=active.device) * (num_rows + 1)
    mat = inverse_inertia.flatten(0, 1).index_add(0, diagonal, reg)
    chosen = start
    for pass_index in range(passes):
        both = (chosen.unsqueeze(1) & chosen.unsqueeze(0)).flatten(0, 1)
        # rows out of the set get an identity row and a zero right-hand side: impulse 0, no coupling
        masked = torch.where(both, mat, 0.0).index_add(0, diagonal, 1.0 - chosen.to(mat.dtype))
        impulse = torch.where(chosen, spatial.spd_solve(masked.view(num_rows, num_rows, -1),
                                                        torch.where(chosen, rhs, 0.0)), 0.0)
        if pass_index + 1 < passes:
            residual = (mat.view(num_rows, num_rows, -1) * impulse.unsqueeze(0)).sum(1) - rhs
            chosen = active & (torch.where(chosen, impulse, -residual) > 0)
    return impulse.clamp_min(0.0)
