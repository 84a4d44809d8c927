"""Equality constraints (MuJoCo ``<equality><tendon>`` and ``<joint>``) as soft constraint forces on the dofs.

Constraint ``e`` relates two sides, each a linear combination of dof coordinates: a fixed tendon's length
``sum_k coef_k q_k`` or a hinge or slide joint's coordinate. With ``x_i`` side ``i`` minus its value at ``qpos0``
(MuJoCo's ``tendon_length0`` or ``qpos0``) and ``P(x) = a0 + a1 x + ... + a4 x^4`` (``polycoef``), the residual is
MuJoCo's ``r = x1 - P(x2)`` (without a second side ``r = x1 - a0``), its rate ``v = v1 - P'(x2) v2`` and its
Jacobian ``J1 - P'(x2) J2``. Like the tendon limits (``torchsim.tendons``), the constraint is MuJoCo's soft
constraint as an explicit force ``f = imp / A0 * (-B v - K imp r)``, in both directions (an equality), entering
side 1 as ``f`` and side 2 as ``-P'(x2) f`` through the sides' coefficients; ``A0`` is MuJoCo's approximate inverse
inertia of the constraint (the sides' ``tendon_invweight0`` or ``dof_invweight0``, summed). What that explicit
force leaves out of MuJoCo's (the ``a0`` term) is said in ``torchsim.tendons``: a steady load holds the constraint
``1 / (1 - imp)`` times further from zero than MuJoCo's does.

Tensors are in the lanes layout: dof quantities ``(D, B)``, constraint quantities ``(E, B)``.
"""

import torch

from torchsim import lanes, tendons
from torchsim.system import System


def residuals(sys: System, q: torch.Tensor, qd: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Each constraint's residual ``r``, its rate ``v`` and ``P'(x2)`` ``(E, B)`` at dof coordinates and rates
    ``q``, ``qd (D, B)``."""
    n = sys.eq_ref.shape[0]
    sides = tendons.combine(q, sys.eq_wrap_side, sys.eq_wrap_dof, sys.eq_wrap_coef, 2 * n)
    rates = tendons.combine(qd, sys.eq_wrap_side, sys.eq_wrap_dof, sys.eq_wrap_coef, 2 * n)
    ref1, ref2 = lanes.param(sys.eq_ref, 2).unbind(-2)
    a0, a1, a2, a3, a4 = lanes.param(sys.eq_polycoef, 2).unbind(-2)
    x1, x2 = sides[:n] - ref1, sides[n:] - ref2
    poly = a0 + x2 * (a1 + x2 * (a2 + x2 * (a3 + x2 * a4)))  # Horner
    slope = a1 + x2 * (2 * a2 + x2 * (3 * a3 + x2 * 4 * a4))
    return x1 - poly, rates[:n] - slope * rates[n:], slope


def add_forces(sys: System, tau: torch.Tensor, q: torch.Tensor, qd: torch.Tensor) -> torch.Tensor:
    """``tau (D, B)`` plus the equality constraints' generalized forces at ``q``, ``qd (D, B)`` (module doc)."""
    r, v, slope = residuals(sys, q, qd)
    f = tendons.soft_force(r, v, sys.eq_gains, sys.eq_solimp, sys.eq_invweight)
    return tendons.spread(tau, torch.cat([f, -slope * f], -2), sys.eq_wrap_side, sys.eq_wrap_dof, sys.eq_wrap_coef)
