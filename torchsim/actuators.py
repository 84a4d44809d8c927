"""Controls and passive joint springs -> generalized forces on hinge/slide dofs, with MuJoCo's semantics."""

import torch

from torchsim import equality, lanes, tendons
from torchsim.system import System


def dof_forces(sys: System, q: torch.Tensor, qd: torch.Tensor, ctrl: torch.Tensor) -> torch.Tensor:
    """Generalized force ``(D, B)`` on every dof for dof coordinates ``q``/``qd (D, B)`` and ``ctrl (U, B)``.

    Actuator force ``gain * ctrl + b0 + b1 * gear * q + b2 * gear * qd``, with ``ctrl`` clamped to ``ctrlrange`` and
    the force to ``forcerange`` where limited, enters the dof as ``gear * force`` (MuJoCo joint transmission).
    Joint springs add ``-stiffness * (q - springref)``. With fixed tendons (``torchsim.tendons``), an actuator
    with tendon transmission acts on ``gear * L`` and ``gear * force`` enters each dof as a tendon force, and the
    tendons' springs, dampers and limits add theirs, and equality constraints (``torchsim.equality``) theirs.
    """
    lo, hi = lanes.param(sys.act_ctrl_range, 2).unbind(-2)
    ctrl = torch.where(lanes.param(sys.act_ctrl_limited, 1), torch.minimum(torch.maximum(ctrl, lo), hi), ctrl)
    with_tendons = sys.ten_springs or sys.ten_limits or sys.act_on_tendons  # inert tendons cost nothing
    act_dof = sys.act_dof.clamp_min(0) if sys.act_on_tendons else sys.act_dof  # -1: tendon transmission
    q_act, qd_act = q.index_select(-2, act_dof), qd.index_select(-2, act_dof)
    if with_tendons:
        length, velocity = tendons.lengths(sys, q), tendons.lengths(sys, qd)
    if sys.act_on_tendons:
        q_act = tendons.actuator_coordinates(sys, q_act, length)
        qd_act = tendons.actuator_coordinates(sys, qd_act, velocity)
    b0, b1, b2 = lanes.param(sys.act_bias, 2).unbind(-2)
    gear = lanes.param(sys.act_gear, 1)
    force = lanes.param(sys.act_gain, 1) * ctrl + b0 + b1 * gear * q_act + b2 * gear * qd_act
    f_lo, f_hi = lanes.param(sys.act_force_range, 2).unbind(-2)
    force = torch.where(lanes.param(sys.act_force_limited, 1), torch.minimum(torch.maximum(force, f_lo), f_hi), force)
    spring = -lanes.param(sys.dof_stiffness, 1) * (q - lanes.param(sys.dof_springref, 1))
    if sys.eq_constraints:  # static: a model without equality constraints skips them
        spring = equality.add_forces(sys, spring, q, qd)
    if not with_tendons:
        return spring.index_add(-2, sys.act_dof, gear * force)
    on_joint = gear * force
    if sys.act_on_tendons:
        on_joint = torch.where(lanes.param(sys.act_tendon < 0, 1), on_joint, 0.0)
    return tendons.add_to_dofs(sys, spring.index_add(-2, act_dof, on_joint),
                               tendons.forces(sys, length, velocity, gear * force))
