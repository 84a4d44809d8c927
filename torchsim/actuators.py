"""Controls and passive joint springs -> generalized forces on hinge/slide dofs, with MuJoCo's semantics."""

import torch

from torchsim import activation, equality, lanes, muscles, rigid, site_actuators, tendon_paths, tendons
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
    clamped to ``ctrlrange`` and the force to ``forcerange`` where limited; a muscle's gain and bias are its
    force-length-velocity curves (``torchsim.muscles``). ``ctrl``: the actuators' inputs, for an
    actuator with activation dynamics its activation (``activation.drive``)."""
    clamped = activation.clamp_ctrl(sys, ctrl)
    if sys.na:  # static: an activation drives its actuator unclamped (MuJoCo clamps it to actrange as it integrates)
        clamped = torch.where(lanes.param(sys.act_adr < 0, 1), clamped, ctrl)
    b0, b1, b2 = lanes.param(sys.act_bias, 2).unbind(-2)
    gain = lanes.param(sys.act_gain, 1)
    if sys.act_muscles:  # static: MuJoCo's muscle curves at the muscles' lengths and velocities
        rows = sys.muscle_gain_actuator
        gain = (gain * torch.ones_like(length)).index_copy(-2, rows, muscles.gains(
            sys, length.index_select(-2, rows), velocity.index_select(-2, rows)))
    force = gain * clamped + b0 + b1 * length + b2 * velocity
    if sys.act_muscles:
        force = force.index_add(-2, sys.muscle_bias_actuator,
                                muscles.biases(sys, length.index_select(-2, sys.muscle_bias_actuator)))
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
    the generalized forces of :func:`dof_forces` as hinge torques and slide forces (``rigid.dof_wrench``), with
    spatial tendons their tensions pulling on their sites (``torchsim.tendon_paths``), and the wrenches of the
    actuators with site transmission at their sites (``torchsim.site_actuators``)."""
    pulling = sys.ten_spatial and tendons.active(sys)
    if not (pulling or sys.act_on_sites):  # static: a model whose forces all act through dofs
        return rigid.dof_wrench(sys, bodies, axes, _dof_and_tendon_forces(sys, q, qd, ctrl)[0])
    path = tendon_paths.paths(sys, bodies) if pulling else None
    site = site_actuators.coordinates(sys, bodies) if sys.act_on_sites else None
    tau, tendon_force, act_force = _dof_and_tendon_forces(sys, q, qd, ctrl, path, site)
    force, torque = rigid.dof_wrench(sys, bodies, axes, tau)
    if pulling:
        pull_force, pull_torque = tendon_paths.wrench(sys, bodies, path, tendon_force)
        force, torque = force + pull_force, torque + pull_torque
    if sys.act_on_sites:
        site_force, site_torque = site_actuators.wrench(sys, bodies, site,
                                                        act_force.index_select(-2, sys.site_act_actuator))
        force, torque = force + site_force, torque + site_torque
    return force, torque


def _dof_and_tendon_forces(sys: System, q: torch.Tensor, qd: torch.Tensor, ctrl: torch.Tensor,
                           path: tendon_paths.Paths | None = None, site: site_actuators.SiteCoordinates | None = None
                           ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
    """:func:`dof_forces`, the tendon forces ``(T, B)`` (None where no tendon acts) and the actuator forces
    ``(U, B)``; ``path``: the spatial tendons' paths, where the System has them, whose lengths and rates add to the
    tendons'; ``site``: the site actuators' lengths and velocities, where the System has them."""
    with_tendons = tendons.active(sys)  # inert tendons cost nothing
    indirect = sys.act_on_tendons or sys.act_on_sites  # static: some actuators act on no dof directly
    act_dof = sys.act_dof.clamp_min(0) if indirect else sys.act_dof  # -1: tendon or site transmission
    if with_tendons:
        length, velocity = tendons.lengths(sys, q), tendons.lengths(sys, qd)
        if path is not None:
            length, velocity = length + path.length, velocity + path.velocity
    gear = lanes.param(sys.act_gear, 1)
    act_length, act_velocity = coordinates(sys, q, qd, *((length, velocity) if sys.act_on_tendons else ()))
    if site is not None:
        act_length = act_length.index_copy(-2, sys.site_act_actuator, site.length)
        act_velocity = act_velocity.index_copy(-2, sys.site_act_actuator, site.velocity)
    force = forces(sys, act_length, act_velocity, ctrl)
    spring = -lanes.param(sys.dof_stiffness, 1) * (q - lanes.param(sys.dof_springref, 1))
    if sys.eq_constraints:  # static: a model without equality constraints skips them
        spring = equality.add_forces(sys, spring, q, qd)
    on_joint = gear * force
    if indirect:
        on_joint = torch.where(lanes.param(sys.act_dof >= 0, 1), on_joint, 0.0)
    tau = spring.index_add(-2, act_dof, on_joint)
    if not with_tendons:
        return tau, None, force
    tendon_force = tendons.forces(sys, length, velocity, gear * force)
    return tendons.add_to_dofs(sys, tau, tendon_force), tendon_force, force
