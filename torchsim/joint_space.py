"""Joint-space terms that MuJoCo keeps in its mass matrix and integrator: armature and joint damping.

In maximal coordinates a dof's armature ``J`` acts like a rotor coupled to the dof's rate: it adds ``J`` to the
inertia every impulse on that dof meets. Each joint's hinge dofs are handled together in the joint's hinge-slot
coordinates (``G = A^-1`` maps a relative rotation onto the slot axes ``A``); joints of one colour run in
parallel and colours in sequence, because dofs of neighbouring joints share a body.

For a slot with armature ``J``, damping ``c`` and rates ``qd_raw`` before, ``qd_ref`` the rotor's rate, the
impulse ``mu`` solves ``(G K G^T + diag(1 / (J + h c))) mu = J qd_ref / (J + h c) - qd_raw`` (``K``: relative
inverse inertia of the joint's bodies): implicit damping, as in MuJoCo's Euler integrator, on a dof whose
inertia includes the armature.
"""

import torch

from torchsim import math, rigid
from torchsim.kinematics import Bodies, JointFrames, dof_values
from torchsim.system import System


def hinge_slots(sys: System, values: torch.Tensor, joints: torch.Tensor | None = None) -> torch.Tensor:
    """Scatter per-dof ``values (..., D)`` onto hinge slots ``(..., J, 3)`` (zero where a slot is no dof)."""
    slot_dof = sys.jnt_slot_dof[:, 3:] if joints is None else sys.jnt_slot_dof[joints, 3:]
    return torch.where(slot_dof >= 0, values[..., slot_dof.clamp_min(0)], 0.0)


def dofs_from_slots(sys: System, slots: torch.Tensor) -> torch.Tensor:
    """Gather ``(B, J, 3)`` hinge-slot values back to ``(B, D)`` (slides read 0)."""
    flat = torch.cat((torch.zeros_like(slots), slots), -1).flatten(1)
    return flat[:, sys.dof_flat]


def hinge_rate_solve(sys: System, bodies: Bodies, inv: rigid.InverseInertia, axes: torch.Tensor,
                     qd_ref: torch.Tensor, damping_h: torch.Tensor):
    """Armature (rotor at rate ``qd_ref (B, J, 3)``) and implicit damping ``damping_h = h c (..., J, 3)`` on every
    joint's hinge slots; ``axes (B, J, 3, 3)`` are the slot axes (rows). Colours are swept forwards and back
    ``sys.joint_sweeps`` times (Gauss-Seidel), accumulating each slot's impulse ``lam`` so the rotor's rate stays
    ``(J qd_ref - lam) / (J + h c)``. Returns bodies and slot rates (B, J, 3)."""
    armature = hinge_slots(sys, sys.dof_armature)
    inertia = armature + damping_h
    include = inertia > 0
    compliance = torch.where(include, 1.0 / inertia.clamp_min(1e-30), 0.0)
    g = math.inv3(axes.transpose(-1, -2))
    lam = torch.zeros_like(qd_ref)
    order = list(sys.jnt_colors) + list(sys.jnt_colors[::-1])
    for colour in order * sys.joint_sweeps:
        child, parent = sys.jnt_child[colour], sys.jnt_parent[colour]
        g_c = g[:, colour]
        _, i_c = rigid.gather(inv, child)
        _, i_p = rigid.gather(inv, parent)
        k_ss = g_c @ (i_c + i_p) @ g_c.transpose(-1, -2)
        qd_raw = math.matvec(g_c, bodies.xd_ang[:, child] - bodies.xd_ang[:, parent])
        mask = include[..., colour, :].to(qd_raw.dtype)
        c = compliance[..., colour, :]
        rhs = mask * (c * (armature[..., colour, :] * qd_ref[:, colour] - lam[:, colour]) - qd_raw)
        mat = mask[..., :, None] * (k_ss + torch.diag_embed(c)) * mask[..., None, :] + torch.diag_embed(1.0 - mask)
        mu = math.matvec(math.inv3(mat), rhs)
        lam = lam.index_add(1, colour, mu)
        p_ang = math.matvec(g_c.transpose(-1, -2), mu)
        zero = torch.zeros_like(p_ang)
        bodies = rigid.apply_pair_velocity(bodies, inv, child, parent, zero, zero, zero, p_ang)
    rates = math.matvec(g, bodies.xd_ang[:, sys.jnt_child] - bodies.xd_ang[:, sys.jnt_parent])
    return bodies, rates


def slide_inertia_and_damping(sys: System, before: Bodies, after: Bodies, axes: torch.Tensor, qd: torch.Tensor,
                              inv: rigid.InverseInertia, h: float):
    """The same for slide dofs, one dof at a time: of the change ``dqd`` forces made, ``dqd / (1 + J w)`` is kept
    (``w = 1/m_c + 1/m_p``), then damping is implicit. Returns bodies and every dof's rate ``(B, D)``."""
    w = rigid.dof_inverse_mass(sys, inv, axes)
    dqd = rigid.dof_rate_change(sys, axes, before, after)
    shrink = 1.0 / (1.0 + sys.dof_armature * w)
    target = (qd + dqd * shrink) / (1.0 + h * sys.dof_damping * w * shrink)
    impulse = torch.where(sys.dof_is_hinge, 0.0, (target - (qd + dqd)) / w)
    return rigid.apply_dof_impulse(sys, after, inv, axes, impulse, position=False), target


def armature_impulse(sys: System, inv: rigid.InverseInertia, axes: torch.Tensor, deviation: torch.Tensor):
    """Impulse ``(B, D)`` giving each dof's armature its share of a constraint's effect ``deviation`` (a rate or a
    coordinate): the constraint moved the dof through the bodies alone; ``1 / (1 + J w)`` of it remains."""
    w = rigid.dof_inverse_mass(sys, inv, axes)
    return -sys.dof_armature * deviation / (1.0 + sys.dof_armature * w)


def inertia_and_damping(sys: System, before: Bodies, after: Bodies, frames: JointFrames, inv: rigid.InverseInertia,
                        h: float):
    """Armature and implicit damping on one substep's force-driven velocity change, for all dofs; ``frames``
    measured at the substep start. Returns bodies and dof rates ``(B, D)``."""
    qd = dof_values(sys, frames.qd)
    after, slot_rates = hinge_rate_solve(sys, after, inv, frames.axes[..., 3:, :], frames.qd[..., 3:],
                                         h * hinge_slots(sys, sys.dof_damping))
    rates = dofs_from_slots(sys, slot_rates)
    if sys.jnt_has_slides:
        after, qd_slides = slide_inertia_and_damping(sys, before, after, dof_values(sys, frames.axes), qd, inv, h)
        rates = torch.where(sys.dof_is_hinge, rates, qd_slides)
    return after, rates
