"""Joint-space terms that MuJoCo keeps in its mass matrix and integrator: armature and joint damping.

In maximal coordinates a dof's armature ``J`` acts like a rotor coupled to the dof's rate: it adds ``J`` to the
inertia every impulse on that dof meets. For dofs with armature ``J``, damping ``c``, rates ``qd_raw`` and rotor
rates ``qd_ref``, the dof impulses ``mu`` solve ``(A + diag(1 / (J + h c))) mu = J qd_ref / (J + h c) - qd_raw``
(``A``: the dofs' inverse inertia through the bodies): implicit damping, as in MuJoCo's Euler integrator, on dofs
whose inertia includes the armature.

Joint ``frictionloss`` (dry friction, MuJoCo's ``dof_frictionloss``) joins the same solve as one more dof impulse,
clamped to ``frictionloss * h`` per substep: it stops the dof when that is enough (stiction), else takes the full
``frictionloss * h`` against the motion (deceleration ``frictionloss / inertia``). A velocity-level impulse, not a
force: an explicit force ``-frictionloss sign(qd)`` flips sign every substep around rest and never holds a dof,
while the clamped impulse holds it exactly in the substep it acts (MuJoCo's soft friction constraint lets a held
dof creep instead). It is sized by the dof's effective inverse inertia with armature and implicit damping, the
inertia every impulse on the dof meets, so a heavy rotor is decelerated at ``frictionloss / (I + J)``. A fixed
tendon's ``frictionloss`` (over hinges) is the same impulse along the tendon's coordinate ``L = sum_k coef_k q_k``:
clamped to ``frictionloss * h``, it enters dof ``k`` as ``coef_k`` times itself.
"""

from typing import NamedTuple

import numpy as np
import torch

from torchsim import lanes, spatial, rigid
from torchsim.kinematics import Bodies, JointFrames, dof_hinge_rows, dof_values
from torchsim.system import System
from torchsim.tendons import impedance


def hinge_incidence(jnt_child, jnt_parent, dof_jnt, dof_is_hinge, num_bodies: int):
    """Load-time tables of the hinge dofs acting on each body (see ``System.body_hinge_dof``): one row per
    (body, hinge) incidence, body ``(P,)``, dof ``(P,)`` and sign ``(P,)`` (+1 for the child, -1 for the parent),
    grouped by body (in dof order within a body); and ``(Q, 2)`` the ordered pairs of incidences on a common body
    (the coupling's blocks). The world (``num_bodies``) takes no impulse and gets no rows."""
    incidences = [(end, dof, sign) for dof, (joint, hinge) in enumerate(zip(dof_jnt, dof_is_hinge)) if hinge
                  for end, sign in ((jnt_child[joint], 1.0), (jnt_parent[joint], -1.0)) if end != num_bodies]
    return incidence_tables(sorted(incidences, key=lambda row: row[:2]))


def incidence_tables(incidences: list):
    """``(body, item, sign)`` incidences, grouped by body, as tensors body ``(P,)``, item ``(P,)``, sign ``(P,)``
    and the ``(Q, 2)`` ordered pairs ``(i, k)`` of incidences on a common body, ``i`` ascending and, for each,
    ``k`` ascending (the blocks of a coupling through the bodies: hinges here, contact points in
    ``torchsim.soft_contacts``). Linear in ``P + Q`` (a body's ``K`` incidences make ``K^2`` pairs)."""
    body, item, sign = (np.array(col) for col in zip(*incidences)) if incidences else (np.zeros(0),) * 3
    return incidence_columns(body, item, sign)


def incidence_columns(body: np.ndarray, item: np.ndarray, sign: np.ndarray):
    """:func:`incidence_tables` of the incidences given as three columns ``(P,)``."""
    body = np.asarray(body).astype(np.int64)
    # each body's incidences in list order, and where row i's body starts among them
    order = np.argsort(body, kind="stable")
    start = np.searchsorted(body[order], body, side="left")
    count = np.searchsorted(body[order], body, side="right") - start
    # pair q of row i is (i, order[start_i + rank]), rank = q - (i's first pair) its place among i's body's rows
    pairs = np.empty((int(count.sum()), 2), dtype=np.int64)
    pairs[:, 0] = np.repeat(np.arange(len(body), dtype=np.int64), count)
    place = np.arange(len(pairs), dtype=np.int64)
    place -= np.repeat(np.cumsum(count) - count - start, count)
    pairs[:, 1] = order[place]
    return (torch.as_tensor(body), torch.as_tensor(np.asarray(item, dtype=np.int64)),
            torch.as_tensor(np.asarray(sign, dtype=np.float64)), torch.as_tensor(pairs))


class LimitRows(NamedTuple):
    """Each dof's soft limit over one substep (:func:`limit_rows`), all ``(D, B)``: ``active`` where the nearer
    side is violated (within its margin), ``sign`` +1 at the lower side (it pushes the coordinate up) and -1 at the
    upper, ``target`` the rate the limit's reference acceleration would reach, ``reg`` MuJoCo's regulariser ``R``."""

    active: torch.Tensor
    sign: torch.Tensor
    target: torch.Tensor
    reg: torch.Tensor


def limit_rows(sys: System, q: torch.Tensor, qd: torch.Tensor, h: float) -> LimitRows:
    """MuJoCo's soft joint limit at dof coordinates and rates ``q, qd (D, B)`` (the substep's start) over a
    substep ``h``.

    MuJoCo's limit force is ``f = max(0, (aref - a0) / (A + R))`` along the limit's direction, ``aref = -B v - K imp
    r`` (``r < 0`` the violation less the margin, ``v`` its rate, ``imp`` the ``solimp`` impedance at ``r``), ``a0``
    the acceleration every other force gives, ``A`` the dof's inverse inertia and ``R = (1 - imp) / imp A0`` (``A0``
    its value at ``qpos0``). As an impulse over ``h`` it is the clamped ``p = max(0, (target - qd_free) / (A +
    R))`` with ``target = qd + h aref`` and ``qd_free`` the rate after every other force: where ``A = A0`` the
    dof reaches ``imp target + (1 - imp) qd_free``, so the violation is released along MuJoCo's spring-damper and a
    steady load settles it where MuJoCo's does (an explicit force without ``a0`` settles ``1 / (1 - imp)``
    deeper, 20x at the default ``solimp``). A range narrower than twice the margin, where MuJoCo has both sides,
    keeps the nearer one."""
    lo, hi = lanes.param(sys.dof_range, 2).unbind(-2)
    below, above = q - lo, hi - q
    lower = below <= above
    sign = 2.0 * lower.to(q.dtype) - 1.0
    r = torch.where(lower, below, above) - lanes.param(sys.dof_margin, 1)
    k, b = lanes.param(sys.dof_limit_gains, 2).unbind(-2)
    imp = impedance(sys.dof_solimp, r, sys.dof_solimp_square)
    target = qd + sign * h * (-b * sign * qd - k * imp * r)
    reg = (1.0 - imp) / imp * lanes.param(sys.dof_invweight, 1)
    return LimitRows(lanes.param(sys.dof_limited, 1) & (r < 0), sign, target, reg)


def hinge_rate_solve(sys: System, bodies: Bodies, inv: rigid.InverseInertia, frames: JointFrames,
                     qd_ref: torch.Tensor, damping_h: torch.Tensor, friction_h: torch.Tensor | None = None,
                     limits: LimitRows | None = None):
    """Armature (a rotor per hinge dof turning at ``qd_ref (D, B)``) and implicit damping ``damping_h = h c
    (D, 1 | B)`` on all hinge dofs at once: one dense ``D x D`` solve per env; with ``friction_h = h frictionloss
    (F + G, 1 | B)`` [N m s | N s] of the frictional hinges ``sys.dof_friction_hinges`` then the frictional
    tendons ``sys.ten_friction``, their dry friction too (:func:`_hinge_friction`); with ``limits``, the soft
    limits (:func:`_limit_system`).

    Dof ``i`` turns its child against its parent about ``u_i``, the row of ``G = A^-1`` for its slot (its axis for
    a single hinge), so ``A_ij = sum_b s_ib s_jb u_i^T I_b^-1 u_j`` (``s = +1`` child, ``-1`` parent) is the dofs'
    inverse inertia through the bodies; dofs sharing a body (the ant's four hips on the torso) are coupled
    exactly, as in MuJoCo's joint-space mass matrix. Only the hinges on each body enter its term (the load-time
    tables ``sys.body_hinge_*``), so building ``A`` costs ``sum_b K_b^2`` products (``K_b`` hinges on body ``b``),
    not ``N D^2``. Returns bodies and every dof's rate ``(D, B)`` (slides 0).
    """
    child, parent = rigid.dof_bodies(sys)
    hinge = lanes.param(sys.dof_is_hinge, 1)
    u = torch.where(hinge, dof_hinge_rows(sys, frames), 0.0)  # (3, D, B)
    n_dof, batch = u.shape[-2], u.shape[-1]
    if n_dof == 0:
        return bodies, u.new_zeros(u.shape[1:])
    dof, body = sys.body_hinge_dof, sys.body_hinge_body
    u_inc = u.index_select(-2, dof) * lanes.param(sys.body_hinge_sign, 1)  # (3, P, B): one per (body, hinge)
    rot = inv.rot.index_select(-2, body)  # I_b^-1 s u through the body frame: cheaper than world inertias
    w_inc = spatial.matvec(rot, spatial.matvec(inv.body.index_select(-2, body), spatial.matvec(spatial.transpose(rot), u_inc)))
    first, second = sys.body_hinge_pairs.unbind(1)
    blocks = spatial.dot(u_inc.index_select(-2, first), w_inc.index_select(-2, second))  # (Q, B)
    a_flat = u.new_zeros(n_dof * n_dof, batch).index_add(0, dof[first] * n_dof + dof[second], blocks)
    armature = torch.where(hinge, lanes.param(sys.dof_armature, 1), 0.0)
    inertia = armature + torch.where(hinge, damping_h, 0.0)
    qd_raw = spatial.dot(u, bodies.xd_ang.index_select(-2, child) - bodies.xd_ang.index_select(-2, parent))
    mat, rhs = _dof_system(a_flat, inertia, armature * qd_ref, qd_raw)
    a = a_flat.view(n_dof, n_dof, batch)
    if limits is not None:
        mat, rhs = _limit_system(a_flat, a, inertia, armature * qd_ref, qd_raw, spatial.spd_solve(mat, rhs),
                                 limits._replace(active=limits.active & hinge))
    mu = spatial.spd_solve(mat, rhs) if friction_h is None else _hinge_friction(sys, mat, a, rhs, qd_raw, friction_h)
    xd_ang = bodies.xd_ang.index_add(-2, body, w_inc * mu.index_select(-2, dof))  # I_b^-1 sum_k s_k u_k mu_k
    return bodies._replace(xd_ang=xd_ang), qd_raw + spatial.matvec(a, mu)


def _dof_system(a_flat: torch.Tensor, inertia: torch.Tensor, momentum: torch.Tensor, qd_raw: torch.Tensor):
    """The matrix ``(D, D, B)`` and right-hand side ``(D, B)`` of the dof impulses ``mu`` for dof elements of
    inertia ``inertia`` and momentum ``momentum`` (``(D, B)``; a rotor: ``J qd_ref``, ``J + h c``): ``(A +
    diag(1 / inertia)) mu = momentum / inertia - qd_raw``, ``A`` from ``a_flat (D * D, B)``."""
    n_dof, batch = qd_raw.shape
    # a dof without an element gets compliance ~1e30 and a zero right-hand side: its impulse is ~1e-30 of the
    # others', i.e. none, and the matrix needs no masking
    compliance = 1.0 / inertia.clamp_min(1e-30)
    rhs = torch.where(inertia > 0, compliance * momentum - qd_raw, 0.0)
    diagonal = torch.arange(n_dof, device=qd_raw.device) * (n_dof + 1)
    return a_flat.index_add(0, diagonal, compliance.expand(n_dof, batch)).view(n_dof, n_dof, batch), rhs


def _limit_system(a_flat: torch.Tensor, a: torch.Tensor, inertia: torch.Tensor, momentum: torch.Tensor,
                  qd_raw: torch.Tensor, mu_free: torch.Tensor, limits: LimitRows):
    """:func:`_dof_system` with the soft limits (:func:`limit_rows`) that push, given the impulses ``mu_free``
    of the system without them.

    A pushing limit ends the substep with ``qd + R p = target`` (``p`` its impulse): on its dof it is an element
    beside the rotor, of inertia ``1 / R`` and momentum ``target / R``, so it joins the same solve through the
    matrix's diagonal and right-hand side, exact where the dofs are coupled. Which limits push is read from the
    rates without limits (``p > 0`` exactly where ``target`` exceeds them, for one limit or uncoupled ones); a
    coupled limit found pushing there that its neighbours' limits would have relieved keeps pushing for this
    substep."""
    free = qd_raw + spatial.matvec(a, mu_free)
    push = limits.active & (limits.sign * (limits.target - free) > 0)
    stiff = torch.where(push, 1.0 / limits.reg, 0.0)
    return _dof_system(a_flat, inertia + stiff, momentum + stiff * limits.target, qd_raw)


def _hinge_friction(sys: System, mat: torch.Tensor, a: torch.Tensor, rhs: torch.Tensor, qd_raw: torch.Tensor,
                     friction_h: torch.Tensor) -> torch.Tensor:
    """The dof impulses ``mu (D, B)`` of :func:`hinge_rate_solve`'s system ``mat mu = rhs`` (``mat (D, D, B)``,
    ``a (D, D, B)`` its part ``A``) with a dry-friction impulse ``p_r``, ``|p_r| <= friction_h_r``, along each
    friction row ``r``: a frictional hinge (``sys.dof_friction_hinges``) or a frictional fixed tendon
    (``sys.ten_friction``). Row ``r`` is a column ``c_r`` of dof coefficients (a unit column for a hinge, the
    tendon's ``coef`` for a tendon, whose rate is ``c_r^T qd``), and its impulse ``p_r`` enters the dofs as
    ``c_r p_r``, as a tendon force does.

    Impulses ``p`` along the rows ``C`` change the dofs' rates by ``W C p``, ``W = A - A mat^-1 A = (A^-1 +
    diag(J + h c))^-1`` (the rotor and damper take their share), and the rotor and damper impulses by ``-mat^-1 A
    C p``; one solve with the columns of ``A C`` as extra right-hand sides gives both. The ``p_r`` then take one
    Gauss-Seidel sweep over the rows, each clamped: exact for one row, or for several that share no body;
    otherwise what one sweep leaves is taken up in the next substep.
    """
    a_c = _friction_rows(sys, a).transpose(0, 1)  # (D, R, B): A C, A symmetric
    x = spatial.spd_solve(mat, torch.cat((rhs.unsqueeze(1), a_c), 1))
    mu, x_c = x[:, 0], x[:, 1:]
    qd = _friction_rows(sys, qd_raw + spatial.matvec(a, mu))  # (R, B)
    w = _friction_rows(sys, a_c) - (a_c.unsqueeze(2) * x_c.unsqueeze(1)).sum(0)  # (R, R, B): C^T W C
    p = []  # (1, B) slices, not (B,) rows: row graphs (torchsim.execution.kernel.rows) cannot read a (1,)-shaped constant
    for k in range(qd.shape[0]):
        row = slice(k, k + 1)
        stop = -(qd[row] + sum(w[row, j] * p[j] for j in range(k))) / w[row, k]
        p.append(torch.minimum(torch.maximum(stop, -friction_h[row]), friction_h[row]))
    p = torch.cat(p)
    hinges = sys.dof_friction_hinges.shape[0]
    mu = mu.index_add(0, sys.dof_friction_hinges, p[:hinges]) - (x_c * p).sum(1)
    if sys.ten_friction.shape[0]:
        terms = lanes.param(sys.ten_friction_coef, 1) * p[hinges:].index_select(0, sys.ten_friction_row)
        mu = mu.index_add(0, sys.ten_friction_dof, terms)
    return mu


def _friction_rows(sys: System, v: torch.Tensor) -> torch.Tensor:
    """``C^T v (R, ...)`` for ``v (D, ...)`` along its first axis: the frictional hinges' entries of ``v``, then
    each frictional tendon's combination ``sum_k coef_k v[dof_k]`` (:func:`_hinge_friction`'s rows ``C``)."""
    hinges = v.index_select(0, sys.dof_friction_hinges)
    if not sys.ten_friction.shape[0]:
        return hinges
    coef = sys.ten_friction_coef.view(-1, *(1,) * (v.ndim - 1))
    terms = coef * v.index_select(0, sys.ten_friction_dof)
    tendons = v.new_zeros((sys.ten_friction.shape[0], *v.shape[1:])).index_add(0, sys.ten_friction_row, terms)
    return torch.cat((hinges, tendons))


def friction_columns(sys: System, n_columns: int) -> torch.Tensor:
    """The frictional rows ``C (n_columns, F + G)`` of :func:`_hinge_friction` (the frictional hinges' unit columns,
    then each frictional tendon's ``coef``) in the first ``D`` of ``n_columns`` columns (the articulation's, whose
    first are the dofs, ``torchsim.articulation``), in :func:`hinge_friction_limits`' order."""
    n_dof = sys.dof_flat.shape[0]
    rows = _friction_rows(sys, torch.eye(n_dof, dtype=sys.dtype, device=sys.device))  # (F + G, D): C^T
    return torch.cat((rows.T, rows.new_zeros(n_columns - n_dof, rows.shape[0])))


def slide_inertia_and_damping(sys: System, before: Bodies, after: Bodies, axes: torch.Tensor, qd: torch.Tensor,
                              inv: rigid.InverseInertia, h: float, limits: LimitRows | None = None):
    """The same for slide dofs, one dof at a time: of the change ``dqd`` forces made, ``dqd / (1 + J w)`` is kept
    (``w = 1/m_c + 1/m_p``), then damping is implicit, then dry friction (``sys.dof_friction_slides``) takes an
    impulse of at most ``h frictionloss`` meeting the effective inverse mass ``w_eff = w / (1 + J w + h c w)``,
    then a violated limit the clamped impulse ``max(0, (target - qd) / (w_eff + R))`` (:func:`limit_rows`).
    ``axes (3, D, B)``, rates ``qd (D, B)``. Returns bodies and every dof's rate ``(D, B)``."""
    w = rigid.dof_inverse_mass(sys, inv, axes)
    dqd = rigid.dof_rate_change(sys, axes, before, after)
    armature, damping = lanes.param(sys.dof_armature, 1), lanes.param(sys.dof_damping, 1)
    shrink = 1.0 / (1.0 + armature * w)
    target = (qd + dqd * shrink) / (1.0 + h * damping * w * shrink)
    w_eff = w / (1.0 + armature * w + h * damping * w)
    if sys.dof_friction_slides:
        limit = h * lanes.param(sys.dof_frictionloss, 1)
        target = target + w_eff * torch.minimum(torch.maximum(-target / w_eff, -limit), limit)
    if limits is not None:
        push = limits.sign * torch.clamp(limits.sign * (limits.target - target), min=0.0)
        target = target + torch.where(limits.active, w_eff * push / (w_eff + limits.reg), 0.0)
    impulse = torch.where(lanes.param(sys.dof_is_hinge, 1), 0.0, (target - (qd + dqd)) / w)
    return rigid.apply_dof_impulse(sys, after, inv, axes, impulse, position=False), target


def armature_impulse(sys: System, inv: rigid.InverseInertia, axes: torch.Tensor, deviation: torch.Tensor):
    """Impulse ``(D, B)`` giving each dof's armature its share of a constraint's effect ``deviation (D, B)`` (a rate
    or a coordinate) along ``axes (3, D, B)``: the constraint moved the dof through the bodies alone; ``1 / (1 + J w)``
    of it remains."""
    w = rigid.dof_inverse_mass(sys, inv, axes)
    armature = lanes.param(sys.dof_armature, 1)
    return -armature * deviation / (1.0 + armature * w)


def hinge_friction_limits(sys: System, h: float) -> torch.Tensor | None:
    """The largest dry-friction impulses ``h frictionloss (F + G, 1 | B)`` [N m s | N s] of the frictional hinges
    then the frictional tendons (:func:`hinge_rate_solve`'s ``friction_h``), None where the model has none."""
    if not (sys.dof_friction_hinges.shape[0] or sys.ten_friction.shape[0]):
        return None
    rows = (lanes.param(sys.dof_frictionloss, 1).index_select(0, sys.dof_friction_hinges),
            lanes.param(sys.ten_frictionloss, 1).index_select(0, sys.ten_friction))
    batch = max(r.shape[-1] for r in rows)  # dof_frictionloss may be per env
    return h * torch.cat([r.expand(-1, batch) for r in rows])


def inertia_and_damping(sys: System, before: Bodies, after: Bodies, frames: JointFrames, inv: rigid.InverseInertia,
                        h: float, q: torch.Tensor | None = None):
    """Armature, implicit damping, dry friction and (given the dof coordinates ``q (D, B)`` at the substep start,
    ``kinematics.dof_angles``) the soft limits on one substep's force-driven velocity change, for all dofs;
    ``frames`` measured at the substep start. Returns bodies and dof rates ``(D, B)``. (XPBD solves the limits in
    its projection instead, where the joints hold: an impulse here turns a link about its COM, and the projection
    would keep only ``I_com / I_pivot`` of it.)"""
    qd = dof_values(sys, frames.qd)
    friction_h = hinge_friction_limits(sys, h)
    limits = None
    if sys.dof_limits and q is not None:
        limits = limit_rows(sys, q, qd, h)
    # slides first: a slide's impulse acts at its child's COM, so its moment turns the parent and changes the rates
    # of the parent's hinges, while a hinge's impulse is a pure torque and changes no slide's rate (the COMs' linear
    # velocities); in this order each solve reads the rates the other leaves. Hinges first, dm_control boxhead's
    # camera pitch limit decided on rates that its kick slide's damping impulse then changed by ~2 mrad/s every
    # substep, and held the camera 0.5 mrad inside its limit where MuJoCo pushes it out (the pitch's RMS error over
    # 0.5 s: 1.7e-3 -> 4.4e-5 rad)
    if sys.jnt_has_slides:
        after, qd_slides = slide_inertia_and_damping(sys, before, after, dof_values(sys, frames.axes), qd, inv, h,
                                                     limits)
    after, rates = hinge_rate_solve(sys, after, inv, frames, qd, h * lanes.param(sys.dof_damping, 1), friction_h,
                                    limits)
    if sys.jnt_has_slides:
        rates = torch.where(lanes.param(sys.dof_is_hinge, 1), rates, qd_slides)
    if sys.root_passive:
        after = root_rate_solve(sys, before, after, frames, inv, h)
    return after, rates


def root_rate_solve(sys: System, before: Bodies, after: Bodies, frames: JointFrames, inv: rigid.InverseInertia,
                    h: float) -> Bodies:
    """Armature, implicit damping and (ball joints) stiffness of free bodies and ball joints over one substep, on
    the rates ``after`` the substep's forces, from the rates ``before`` them (the rotors' rates); ``frames`` at the
    substep's start.

    MJCF gives each of these joints one damping ``d`` and armature ``J`` for all its dofs, so with ``k = J + h d``
    the rotor and damper add ``k`` to every dof's inertia and ``J`` times the rotor's rate to its momentum, as for
    the hinges (:func:`hinge_rate_solve`).

    A free body's dofs are the velocity ``v_o`` of its frame's origin (``r`` from the COM, world frame) and its
    angular velocity ``w``: with ``(v, w)`` at the COM, ``v_o = v + w x r``, the body's momentum equations gain
    ``k (v_o, r x v_o) + (0, k w)``, i.e. ``(m + k) v - k r x w = p`` and ``k r x v + (I + k - k [r]x^2) w = L``
    (``p = m v_raw + J v_o,ref``, ``L = I w_raw + r x J v_o,ref + J w_ref``), solved by eliminating ``v``: one 3x3
    solve per body. Gravity then accelerates a body with armature at ``m / (m + J)`` of ``g``, as in MuJoCo. (The
    rotor's rate is re-read each substep, exact where its linear part does not turn with the body: the loader
    refuses armature on a free body whose origin is off its COM.)

    A ball joint's rotor turns with the child's rate relative to the parent: the impulse ``mu`` it and the damper
    take solves ``(k A + 1) mu = J w_ref - k w_raw`` (``A`` the child's and parent's inverse inertias about their
    COMs, as the hinges', exact for a child whose COM is at the pivot), and the spring adds the impulse ``-h K
    log(q_spring^-1 q)`` (MuJoCo's ``mju_subQuat``, child frame) before it.
    """
    if sys.free_body.shape[0]:
        body = sys.free_body
        mass = lanes.param(sys.body_mass, 1).index_select(-2, body)
        rot = inv.rot.index_select(-2, body)
        inertia = spatial.mm(rot, lanes.param(sys.body_inertia, 1, 2).index_select(-2, body), spatial.transpose(rot))
        arm = spatial.matvec(rot, lanes.param(sys.free_origin, 1, 1))
        armature = lanes.param(sys.free_armature, 1)
        k = armature + h * lanes.param(sys.free_damping, 1)
        v_raw, w_raw = after.xd_vel.index_select(-2, body), after.xd_ang.index_select(-2, body)
        w_ref = before.xd_ang.index_select(-2, body)
        rotor = armature * (before.xd_vel.index_select(-2, body) + spatial.cross(w_ref, arm))  # J v_o,ref
        p = mass * v_raw + rotor
        l_ang = spatial.matvec(inertia, w_raw) + spatial.cross(arm, rotor) + armature * w_ref
        share = k / (mass + k)
        lever = spatial.outer(arm, arm) - spatial.dot(arm, arm) * spatial.eye3(arm, 2)  # [r]x^2
        schur = inertia + k * spatial.eye3(arm, 2) - (share * mass) * lever
        w = spatial.matvec(spatial.inv3(schur), l_ang - share * spatial.cross(arm, p))
        v = (p + k * spatial.cross(arm, w)) / (mass + k)
        after = after._replace(xd_vel=after.xd_vel.index_copy(-2, body, v),
                               xd_ang=after.xd_ang.index_copy(-2, body, w))
    if sys.ball_joint.shape[0]:
        joint = sys.ball_joint
        child, parent = sys.jnt_child[joint], sys.jnt_parent[joint]
        inv_c, inv_p = inv.inertia.index_select(-2, child), inv.inertia.index_select(-2, parent)
        armature = lanes.param(sys.ball_armature, 1)
        k = armature + h * lanes.param(sys.ball_damping, 1)
        offset = spatial.quat_mul(spatial.quat_conj(lanes.param(sys.ball_spring, 1, 1)),
                                  frames.quat_rel.index_select(-2, joint))
        spring = spatial.quat_rotate(before.x_quat.index_select(-2, child),
                                     -h * lanes.param(sys.ball_stiffness, 1) * spatial.quat_to_rot_vec(offset))
        a = inv_c + inv_p
        w_raw = (after.xd_ang.index_select(-2, child) - after.xd_ang.index_select(-2, parent)
                 + spatial.matvec(a, spring))
        w_ref = before.xd_ang.index_select(-2, child) - before.xd_ang.index_select(-2, parent)
        mu = spatial.matvec(spatial.inv3(k * a + spatial.eye3(a, 2)), armature * w_ref - k * w_raw)
        impulse = mu + spring
        after = after._replace(xd_ang=after.xd_ang.index_add(-2, child, spatial.matvec(inv_c, impulse))
                               .index_add(-2, parent, -spatial.matvec(inv_p, impulse)))
    return after


def armature_loaded_inertia(sys: System, inv: rigid.InverseInertia, axes: torch.Tensor) -> rigid.InverseInertia:
    """Inverse inertias in which each child body also carries its hinges' armature ``J a a^T`` (world frame), for
    dof ``axes (3, D, B)`` at the poses ``inv`` was built for.

    Contacts use these: an impulse on a light link whose hinge has a heavy armature turns it about the hinge as
    if the rotor were attached. The rotor is relative to the parent, this is relative to the world: exact while
    the parent does not turn about the hinge axis, and in any case it only shapes how a contact impulse divides
    between rotation and translation.

    Without 2- or 3-hinge joints no body is the child of more than one hinge, so each child's inverse takes one
    rank-1 (Sherman-Morrison) update, ``W - J (W a)(W a)^T / (1 + J a^T W a)`` from ``W = inv.inertia``;
    otherwise the loaded inertias are built and inverted.
    """
    child, _ = rigid.dof_bodies(sys)
    hinge_armature = torch.where(lanes.param(sys.dof_is_hinge, 1), lanes.param(sys.dof_armature, 1), 0.0)
    _, _, two, three, _ = sys.jnt_kinds
    if not (two or three):
        w_axis = spatial.matvec(inv.inertia.index_select(-2, child), axes)
        update = hinge_armature / (1.0 + hinge_armature * spatial.dot(axes, w_axis)) * spatial.outer(w_axis, w_axis)
        return inv._replace(inertia=inv.inertia.index_add(-2, child, -update), body=None)
    rot = inv.rot[..., :-1, :]
    inertia = spatial.mm(rot, lanes.param(sys.body_inertia, 1, 2), spatial.transpose(rot))
    inertia = inertia.index_add(-2, child, hinge_armature * spatial.outer(axes, axes))
    inv_world = torch.cat((spatial.inv3(inertia), torch.zeros_like(inv.inertia[..., :1, :])), -2)
    return inv._replace(inertia=inv_world, body=None)
