"""Tendons: lengths of fixed tendons, and the tendon forces of passive springs and dampers, soft limits and
actuators with tendon transmission.

A fixed tendon's (MuJoCo ``<tendon><fixed>``) length is ``L = sum_k coef_k q_k`` [m | rad] and a tendon force ``f``
enters dof ``k`` as ``coef_k f``. A spatial tendon's length is its path through sites, and its force pulls on the
sites' bodies (``torchsim.tendon_paths``); its springs, dampers and actuators are those of this module, its limits
these with MuJoCo's ``a0`` term (below; ``tendon_paths.limit_wrench``).
Tensors are in the lanes layout: dof quantities ``(D, B)``, tendon quantities ``(T, B)``, actuators ``(U, B)``.

A fixed tendon's limits follow MuJoCo's soft constraint without its solver: where a side of the range is violated
(within ``margin``), the limit pushes with ``f = max(0, imp / A0 * aref)``, ``aref = -B v - K imp r`` (``r <= 0`` the
violation, ``v`` its rate, ``imp`` the ``solimp`` impedance at ``r``, ``A0`` MuJoCo's tendon inverse inertia
at ``qpos0``). MuJoCo's force is ``(aref - a0) / (A + (1 - imp) / imp A0)``, with ``a0`` the acceleration every
other force gives the tendon: this explicit force leaves out that term, so under a steady load ``F`` the limit
settles at ``r = -A0 F / (imp^2 K)`` where MuJoCo's settles ``1 - imp`` times as deep (default ``solimp``: 5 %),
while the free motion into and out of the limit (``a = -imp (B v + K imp r)``) is MuJoCo's (both where the
tendon's inverse inertia ``A`` is ``A0``). A spatial tendon's limits take ``a0`` from the forces on the sites'
bodies, ``imp / A0 (aref - a0)``: MuJoCo's force where ``A`` is ``A0``.
"""

import torch

from torchsim import lanes
from torchsim.system import System


def active(sys: System) -> bool:
    """Whether any tendon exerts a force: a spring or damper, a limit or an actuator (static structure)."""
    return sys.ten_springs or sys.ten_limits or sys.act_on_tendons


def lengths(sys: System, x: torch.Tensor) -> torch.Tensor:
    """Fixed tendon lengths ``(T, B)`` for dof coordinates ``x (D, B)`` (or their rates for the tendons' rates); 0 for
    spatial tendons (``torchsim.tendon_paths``)."""
    return combine(x, sys.ten_wrap_tendon, sys.ten_wrap_dof, sys.ten_wrap_coef, sys.ten_limited.shape[0])


def add_to_dofs(sys: System, tau: torch.Tensor, force: torch.Tensor) -> torch.Tensor:
    """``tau (D, B)`` plus the generalized forces of tendon forces ``force (T, B)`` [N | N m]."""
    return spread(tau, force, sys.ten_wrap_tendon, sys.ten_wrap_dof, sys.ten_wrap_coef)


def combine(x: torch.Tensor, row: torch.Tensor, dof: torch.Tensor, coef: torch.Tensor, rows: int) -> torch.Tensor:
    """``rows`` linear combinations ``(R, B)`` of dof coordinates ``x (D, B)``: term ``k`` adds ``coef[k] *
    x[dof[k]]`` to row ``row[k]`` (the tendons' lengths, the equality constraints' sides)."""
    terms = lanes.param(coef, 1) * x.index_select(-2, dof)
    return x.new_zeros((rows, x.shape[-1])).index_add(-2, row, terms)


def spread(tau: torch.Tensor, force: torch.Tensor, row: torch.Tensor, dof: torch.Tensor,
           coef: torch.Tensor) -> torch.Tensor:
    """``tau (D, B)`` plus the generalized forces of forces ``(R, B)`` along the rows of :func:`combine`."""
    return tau.index_add(-2, dof, lanes.param(coef, 1) * force.index_select(-2, row))


def actuator_coordinates(sys: System, joint: torch.Tensor, tendon: torch.Tensor) -> torch.Tensor:
    """Each actuator's transmission coordinate (before ``gear``) ``(U, B)``: its tendon's entry of ``tendon
    (T, B)`` for tendon transmission, else its entry ``joint (U, B)`` (the dof coordinate)."""
    on_tendon = lanes.param(sys.act_tendon >= 0, 1)
    return torch.where(on_tendon, tendon.index_select(-2, sys.act_tendon.clamp_min(0)), joint)


def forces(sys: System, length: torch.Tensor, velocity: torch.Tensor, act_force: torch.Tensor) -> torch.Tensor:
    """Tendon forces ``(T, B)`` [N | N m] at lengths and rates ``(T, B)``: passive springs and dampers, limits, and
    ``act_force (U, B)`` (``gear * force``) of the actuators with tendon transmission."""
    force = torch.zeros_like(length)
    if sys.ten_springs:
        lo, hi = lanes.param(sys.ten_lengthspring, 2).unbind(-2)
        stretch = torch.clamp(length - hi, min=0.0) + torch.clamp(length - lo, max=0.0)  # zero in the dead band
        force = force - lanes.param(sys.ten_stiffness, 1) * stretch - lanes.param(sys.ten_damping, 1) * velocity
    if sys.ten_limits:
        force = force + limit_forces(sys, length, velocity)
    if sys.act_on_tendons:
        on_tendon = lanes.param(sys.act_tendon >= 0, 1)
        force = force.index_add(-2, sys.act_tendon.clamp_min(0), torch.where(on_tendon, act_force, 0.0))
    return force


def limit_forces(sys: System, length: torch.Tensor, velocity: torch.Tensor,
                 a0: torch.Tensor | None = None) -> torch.Tensor:
    """The limits' tendon forces ``(T, B)``: each side of the range as MuJoCo's soft constraint (module doc), the
    fixed tendons' explicit (``a0`` None); or with ``a0 (T, B)``, the acceleration the other forces give each
    tendon's length (MuJoCo's ``a0``, ``tendon_paths.limit_wrench``), the spatial tendons' with that term."""
    lo, hi = lanes.param(sys.ten_range, 2).unbind(-2)
    margin = lanes.param(sys.ten_margin, 1)
    limited = lanes.param(sys.ten_limited & (~sys.ten_is_spatial if a0 is None else sys.ten_is_spatial), 1)
    total = torch.zeros_like(length)
    for sign, dist in ((1.0, length - lo), (-1.0, hi - length)):  # lower side, upper side
        r = dist - margin
        push = soft_force(r, sign * velocity, sys.ten_limit_gains, sys.ten_solimp, sys.ten_invweight,
                          None if a0 is None else sign * a0)
        total = total + sign * torch.where(limited & (r < 0), torch.clamp(push, min=0.0), 0.0)
    return total


def soft_force(r: torch.Tensor, v: torch.Tensor, gains: torch.Tensor, solimp: torch.Tensor,
               invweight: torch.Tensor, a0: torch.Tensor | None = None) -> torch.Tensor:
    """MuJoCo's soft constraint as an explicit force ``(C, B)`` along ``C`` constraints (tendon limits, equality
    constraints) at violations ``r`` and their rates ``v (C, B)``: ``imp / A0 * (-B v - K imp r)`` (module doc), with
    the System fields ``gains (C, 2)`` (``K``, ``B``), ``solimp (C, 5)`` and ``invweight (C,)`` (``A0``); with
    ``a0 (C, B)``, the acceleration the other forces give the constraints, MuJoCo's ``imp / A0 * (aref - a0)``, its
    force ``(aref - a0) / (A + R)`` where ``A = A0``. A limit takes its positive part; an equality constraint all of
    it."""
    k, b = lanes.param(gains, 2).unbind(-2)
    imp = impedance(solimp, r)
    aref = -b * v - k * imp * r
    return imp / lanes.param(invweight, 1) * (aref if a0 is None else aref - a0)


def impedance(solimp: torch.Tensor, r: torch.Tensor, square: bool = False) -> torch.Tensor:
    """MuJoCo's impedance ``(C, B)`` at violations ``r (C, B)`` for the System field ``solimp (C, 5)``: from ``dmin``
    at ``r = 0`` to ``dmax`` at ``|r| >= width`` along a two-piece power curve with its knee at ``midpoint``.
    ``square`` (static): every ``power`` is 2, MuJoCo's default, whose curve needs no exp and log."""
    dmin, dmax, width, mid, power = lanes.param(solimp, 2).unbind(-2)
    x = torch.clamp(r.abs() / width, max=1.0)
    # rising x^p / mid^(p - 1) below the knee, falling 1 - (1 - x)^p / (1 - mid)^(p - 1) above it: one branch's
    # powers as exp(p log base - (p - 1) log scale) (the C++ step kernel has exp and log but no pow)
    above = x > mid
    base = torch.where(above, 1 - x, x)
    scale = torch.where(above, 1 - mid, mid)
    if square:  # the calls to exp and log cost the ant's compiled step 10%, as much as its other limit work
        power_ratio = base * base / scale
    else:
        power_ratio = torch.exp(power * torch.log(torch.clamp(base, min=1e-30)) - (power - 1) * torch.log(scale))
    y = torch.where(above, 1 - power_ratio, power_ratio)
    flat = (dmin == dmax) | (width <= 1e-15)  # MuJoCo's flat impedance
    imp = torch.where(flat, 0.5 * (dmin + dmax), dmin + y * (dmax - dmin))
    return torch.clamp(imp, min=1e-4, max=0.9999)
