"""Actuator activation dynamics (MuJoCo's ``dyntype``): each activated actuator's state ``act``, its rate
``act_dot`` and its update over a step, with MuJoCo's semantics.

MuJoCo computes ``act_dot`` once per step from the step's controls and activations, drives the actuator with
``act`` (or, with ``actearly``, with the activation the step will end at), and integrates ``act`` once at the end of
the step (``mj_Euler``: ``act + h act_dot``, or ``filterexact``'s exact exponential), clamped to ``actrange`` where
``actlimited``. ``torchsim.pipeline.run_substeps`` does the same around its substeps: ``act`` is constant over a
step's substeps, as MuJoCo holds it over its step.

Tensors are in the lanes layout: activations ``(A, B)``, controls ``(U, B)``.
"""

import torch

from torchsim import lanes
from torchsim.system import System

#: MuJoCo's dyntypes with an activation state, in ``mjtDyn`` order from ``integrator`` (``System.activation_kind``
#: indexes this tuple).
ACTIVATION_KINDS = ("integrator", "filter", "filterexact", "muscle")

#: MuJoCo's ``mjMINVAL``: the smallest time constant, smoothing width and timescale its dynamics divide by.
MIN_VALUE = 1e-15


def clamp_ctrl(sys: System, ctrl: torch.Tensor) -> torch.Tensor:
    """``ctrl (U, B)`` clamped to ``ctrlrange`` where ``ctrllimited``, as MuJoCo clamps it before using it."""
    lo, hi = lanes.param(sys.act_ctrl_range, 2).unbind(-2)
    return torch.where(lanes.param(sys.act_ctrl_limited, 1), torch.minimum(torch.maximum(ctrl, lo), hi), ctrl)


def rates(sys: System, ctrl: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
    """MuJoCo's ``act_dot (A, B)`` for controls ``ctrl (U, B)`` and activations ``act (A, B)``: ``integrator``
    ``ctrl``, ``filter`` and ``filterexact`` ``(ctrl - act) / tau``, ``muscle`` :func:`muscle_rates`."""
    u = clamp_ctrl(sys, ctrl).index_select(-2, sys.activation_actuator)
    kind = lanes.param(sys.activation_kind, 1)
    prm = lanes.param(sys.activation_dynprm, 1, 1)
    rate = u  # integrator; the kinds the model lacks are not computed (activation_kinds is static)
    if "filter" in sys.activation_kinds or "filterexact" in sys.activation_kinds:
        filtered = (u - act) / prm[0].clamp_min(MIN_VALUE)
        rate = torch.where((kind == ACTIVATION_KINDS.index("filter")) | (kind == ACTIVATION_KINDS.index("filterexact")),
                           filtered, rate)
    if "muscle" in sys.activation_kinds:
        rate = torch.where(kind == ACTIVATION_KINDS.index("muscle"), muscle_rates(u, act, prm), rate)
    return rate


def muscle_rates(ctrl: torch.Tensor, act: torch.Tensor, prm: torch.Tensor) -> torch.Tensor:
    """MuJoCo's muscle activation rate (Millard et al. 2013): ``(ctrl - act) / tau`` with ``ctrl`` clamped to
    [0, 1], ``tau`` the activation time constant ``prm[0] (0.5 + 1.5 a)`` when ``ctrl`` exceeds ``act`` and the
    deactivation one ``prm[1] / (0.5 + 1.5 a)`` otherwise (``a``: ``act`` clamped to [0, 1]); with a smoothing width
    ``prm[2] > 0`` a quintic sigmoid of ``(ctrl - act) / width + 1/2`` blends the two instead of switching."""
    a = act.clamp(0.0, 1.0)
    tau_act, tau_deact = prm[0] * (0.5 + 1.5 * a), prm[1] / (0.5 + 1.5 * a)
    excess = ctrl.clamp(0.0, 1.0) - act
    x = (excess / prm[2].clamp_min(MIN_VALUE) + 0.5).clamp(0.0, 1.0)
    sigmoid = x * x * x * (x * (6.0 * x - 15.0) + 10.0)  # 0 at x <= 0, 1 at x >= 1, C2 between
    smooth = tau_deact + (tau_act - tau_deact) * sigmoid
    tau = torch.where(prm[2] < MIN_VALUE, torch.where(excess > 0, tau_act, tau_deact), smooth)
    return excess / tau.clamp_min(MIN_VALUE)


def advance(sys: System, act: torch.Tensor, rate: torch.Tensor) -> torch.Tensor:
    """The activations ``(A, B)`` one ``sys.timestep`` after ``act`` at rates ``rate`` (MuJoCo's
    ``mj_nextActivation``): ``act + h rate``, for ``filterexact`` ``act + rate tau (1 - exp(-h / tau))`` (the exact
    step of the first-order filter), clamped to ``actrange`` where ``actlimited``."""
    h = sys.timestep
    step = h * rate
    if "filterexact" in sys.activation_kinds:  # static
        tau = lanes.param(sys.activation_dynprm[:, 0], 1).clamp_min(MIN_VALUE)
        exact = lanes.param(sys.activation_kind, 1) == ACTIVATION_KINDS.index("filterexact")
        step = torch.where(exact, rate * tau * -torch.expm1(-h / tau), step)
    new = act + step
    lo, hi = lanes.param(sys.activation_range, 2).unbind(-2)
    return torch.where(lanes.param(sys.activation_limited, 1), torch.minimum(torch.maximum(new, lo), hi), new)


def drive(sys: System, ctrl: torch.Tensor, act: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """What drives each actuator over a step from activations ``act (A, B)`` under controls ``ctrl (U, B)``, and the
    activations ``(A, B)`` the step ends at (:func:`advance`). An actuator is driven by its control, or with
    activation dynamics by its activation, with ``actearly`` by the one the step ends at (MuJoCo's force ``gain *
    act + bias``); ``torchsim.actuators.forces`` clamps only the controls to ``ctrlrange``."""
    act_next = advance(sys, act, rates(sys, ctrl, act))
    driving = torch.where(lanes.param(sys.activation_early, 1), act_next, act)
    return ctrl.index_copy(-2, sys.activation_actuator, driving), act_next
