"""Controls and passive joint springs -> generalized forces on hinge/slide dofs, with MuJoCo's semantics."""

import torch

from torchsim import equality, lanes, rigid, tendon_paths, tendons
from torchsim.kinematics import Bodies
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
    """Generalized force ``(D, B)`` on every dof for dof coordinates ``q``/``qd (D, B)`` and ``ctrl (U, B)``, for a
    System without spatial tendons (whose forces act on bodies: :func:`body_wrench`).

    Actuator force (:func:`forces` at :func:`coordinates`) enters the dof as ``gear * force`` (MuJoCo joint
    transmission).
    Joint springs add ``-stiffness * (q - springref)``. With fixed tendons (``torchsim.tendons``), an actuator
    with tendon transmission acts on ``gear * L`` and ``gear * force`` enters each dof as a tendon force, and the
    tendons' springs, dampers and limits add theirs, and equality constraints (``torchsim.equality``) theirs.
    """
    if sys.ten_spatial:
        raise ValueError("the System has spatial tendons, whose forces act on bodies: use actuators.body_wrench")
    return _dof_and_tendon_forces(sys, q, qd, ctrl)[0]


def body_wrench(sys: System, bodies: Bodies, axes: torch.Tensor, q: torch.Tensor, qd: torch.Tensor,
                ctrl: torch.Tensor):
    """Ext-indexed ``(force, torque)`` ``(3, N + 1, B)`` of the actuators, passive springs, tendons and equality
    constraints at lanes ``bodies``, dof ``axes (3, D, B)``, dof coordinates ``q``/``qd (D, B)`` and ``ctrl (U, B)``:
    the generalized forces of :func:`dof_forces` as hinge torques and slide forces (``rigid.dof_wrench``), and
    with spatial tendons their tensions pulling on their sites (``torchsim.tendon_paths``)."""
    if not (sys.ten_spatial and tendons.active(sys)):  # static: a model without acting spatial tendons
        return rigid.dof_wrench(sys, bodies, axes, _dof_and_tendon_forces(sys, q, qd, ctrl)[0])
    path = tendon_paths.paths(sys, bodies)
    tau, tendon_force = _dof_and_tendon_forces(sys, q, qd, ctrl, path)
    force, torque = rigid.dof_wrench(sys, bodies, axes, tau)
    pull_force, pull_torque = tendon_paths.wrench(sys, bodies, path, tendon_force)
    return force + pull_force, torque + pull_torque


def _dof_and_tendon_forces(sys: System, q: torch.Tensor, qd: torch.Tensor, ctrl: torch.Tensor,
                           path: tendon_paths.Paths | None = None) -> tuple[torch.Tensor, torch.Tensor | None]:
    """:func:`dof_forces` and the tendon forces ``(T, B)`` (None where no tendon acts); ``path``: the spatial
    tendons' paths, where the System has them, whose lengths and rates add to the tendons'."""
    with_tendons = tendons.active(sys)  # inert tendons cost nothing
    act_dof = sys.act_dof.clamp_min(0) if sys.act_on_tendons else sys.act_dof  # -1: tendon transmission
    if with_tendons:
        length, velocity = tendons.lengths(sys, q), tendons.lengths(sys, qd)
        if path is not None:
            length, velocity = length + path.length, velocity + path.velocity
    gear = lanes.param(sys.act_gear, 1)
    force = forces(sys, *coordinates(sys, q, qd, *((length, velocity) if sys.act_on_tendons else ())), ctrl)
    spring = -lanes.param(sys.dof_stiffness, 1) * (q - lanes.param(sys.dof_springref, 1))
    if sys.eq_constraints:  # static: a model without equality constraints skips them
        spring = equality.add_forces(sys, spring, q, qd)
    if not with_tendons:
        return spring.index_add(-2, sys.act_dof, gear * force), None
    on_joint = gear * force
    if sys.act_on_tendons:
        on_joint = torch.where(lanes.param(sys.act_tendon < 0, 1), on_joint, 0.0)
    tendon_force = tendons.forces(sys, length, velocity, gear * force)
    return tendons.add_to_dofs(sys, spring.index_add(-2, act_dof, on_joint), tendon_force), tendon_force
