"""Controls and passive joint springs -> generalized forces on hinge/slide dofs, with MuJoCo's semantics."""

import torch

from torchsim import equality, lanes, tendons
from torchsim.system import System


def coordinates(sys: System, q: torch.Tensor, qd: torch.Tensor, tendon_length: torch.Tensor | None = None,
                tendon_velocity: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """MuJoCo's ``actuator_length`` and ``actuator_velocity`` ``(U, B)`` at dof coordinates ``q, qd (D, B)``: ``gear``
    times the joint's coordinate, or the tendon's (``tendon_length``/``tendon_velocity`` ``(T, B)`` where the
    caller has them)."""
    act_dof = sys.act_dof.clamp_min(0)  # -1: tendon transmission
    joint = [x.index_select(-2, act_dof) for x in (q, qd)]
    if sys.act_on_tendons:  # static: a model without tendon actuators may have no tendons to index
        tendon = (tendon_length, tendon_velocity) if tendon_length is not None else (
            tendons.lengths(sys, q), tendons.lengths(sys, qd))
        joint = [tendons.actuator_coordinates(sys, j, t) for j, t in zip(joint, tendon)]
    gear = lanes.param(sys.act_gear, 1)
    return gear * joint[0], gear * joint[1]


def forces(sys: System, length: torch.Tensor, velocity: torch.Tensor, ctrl: torch.Tensor) -> torch.Tensor:
    """MuJoCo's ``actuator_force`` ``(U, B)``: ``gain * ctrl + b0 + b1 * length + b2 * velocity``, with ``ctrl``
    clamped to ``ctrlrange`` and the force to ``forcerange`` where limited."""
    lo, hi = lanes.param(sys.act_ctrl_range, 2).unbind(-2)
    ctrl = torch.where(lanes.param(sys.act_ctrl_limited, 1), torch.minimum(torch.maximum(ctrl, lo), hi), ctrl)
    b0, b1, b2 = lanes.param(sys.act_bias, 2).unbind(-2)
    force = lanes.param(sys.act_gain, 1) * ctrl + b0 + b1 * length + b2 * velocity
    f_lo, f_hi = lanes.param(sys.act_force_range, 2).unbind(-2)
    return torch.where(lanes.param(sys.act_force_limited, 1), torch.minimum(torch.maximum(force, f_lo), f_hi), force)


def dof_forces(sys: System, q: torch.Tensor, qd: torch.Tensor, ctrl: torch.Tensor) -> torch.Tensor:
    """Generalized force ``(D, B)`` on every dof for dof coordinates ``q``/``qd (D, B)`` and ``ctrl (U, B)``.

    Actuator force (:func:`forces` at :func:`coordinates`) enters the dof as ``gear * force`` (MuJoCo joint
    transmission).
    Joint springs add ``-stiffness * (q - springref)``. With fixed tendons (``torchsim.tendons``), an actuator
    with tendon transmission acts on ``gear * L`` and ``gear * force`` enters each dof as a tendon force, and the
    tendons' springs, dampers and limits add theirs, and equality constraints (``torchsim.equality``) theirs.
    """
    with_tendons = sys.ten_springs or sys.ten_limits or sys.act_on_tendons  # inert tendons cost nothing
    act_dof = sys.act_dof.clamp_min(0) if sys.act_on_tendons else sys.act_dof  # -1: tendon transmission
    if with_tendons:
        length, velocity = tendons.lengths(sys, q), tendons.lengths(sys, qd)
    gear = lanes.param(sys.act_gear, 1)
    force = forces(sys, *coordinates(sys, q, qd, *((length, velocity) if sys.act_on_tendons else ())), ctrl)
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
