"""MuJoCo's muscle gain and bias (``gaintype``/``biastype`` muscle): the force-length-velocity curves that make an
actuator's force ``gain(L, V) act + bias(L)`` a muscle's.

A muscle's parameters (MuJoCo's ``gainprm``/``biasprm``) are its operating range of normalised lengths, its peak
force ``F0`` [N], the lengths ``lmin``, ``lmax`` where its active force vanishes, the shortening velocity ``vmax``
[L0/s] at which it does, the passive force ``fpmax`` [F0] at ``lmax`` and the lengthening force ``fvmax`` [F0].
Its length ``L`` [m] is normalised over its ``lengthrange`` (MuJoCo's ``actuator_lengthrange``, computed when it
compiles the model) onto the operating range: ``l = range[0] + (L - lengthrange[0]) / L0``, ``L0 = (lengthrange[1] -
lengthrange[0]) / (range[1] - range[0])``, and its velocity ``v = V / (L0 vmax)``. Then (MuJoCo's curves)

- active force-length ``FL(l)``: 0 outside ``[lmin, lmax]``, 1 at ``l = 1``, two half-parabolas up from each end
  to the midpoints ``(lmin + 1) / 2`` and ``(1 + lmax) / 2`` and two down from 1;
- force-velocity ``FV(v)``: 0 at ``v <= -1``, ``(v + 1)^2`` up to 0, then ``fvmax - (fvmax - 1 - v)^2 / (fvmax - 1)``
  up to ``fvmax - 1``, ``fvmax`` beyond;
- passive force-length ``FP(l)``: 0 up to ``l = 1``, a half-parabola reaching ``fpmax / 2`` at ``b = (1 + lmax) / 2``,
  linear beyond (slope ``fpmax / (b - 1)``);

and ``gain = -F0 FL FV``, ``bias = -F0 FP``: a muscle pulls (negative force along its length).

Tensors are in the lanes layout: per muscle ``(M, B)``; parameters ``(9, M, 1)``.
"""

import torch

from torchsim import lanes
from torchsim.activation import MIN_VALUE
from torchsim.system import System


def _normalised(prm: torch.Tensor, length_range: torch.Tensor, length: torch.Tensor, velocity: torch.Tensor):
    """``(l, v)``: ``length`` and ``velocity`` normalised by the optimal length ``L0`` (module doc)."""
    optimal = (length_range[1] - length_range[0]) / (prm[1] - prm[0]).clamp_min(MIN_VALUE)
    optimal = optimal.clamp_min(MIN_VALUE)
    return prm[0] + (length - length_range[0]) / optimal, velocity / (optimal * prm[6]).clamp_min(MIN_VALUE)


def _half_parabola(x: torch.Tensor) -> torch.Tensor:
    return 0.5 * x * x


def _active_length(l: torch.Tensor, lmin: torch.Tensor, lmax: torch.Tensor) -> torch.Tensor:
    """``FL(l)``, MuJoCo's active force-length curve."""
    a, b = 0.5 * (lmin + 1.0), 0.5 * (1.0 + lmax)
    rising = torch.where(l <= a, _half_parabola((l - lmin) / (a - lmin).clamp_min(MIN_VALUE)),
                         1.0 - _half_parabola((1.0 - l) / (1.0 - a).clamp_min(MIN_VALUE)))
    falling = torch.where(l <= b, 1.0 - _half_parabola((l - 1.0) / (b - 1.0).clamp_min(MIN_VALUE)),
                          _half_parabola((lmax - l) / (lmax - b).clamp_min(MIN_VALUE)))
    return torch.where((l < lmin) | (l > lmax), 0.0, torch.where(l <= 1.0, rising, falling))


def _velocity(v: torch.Tensor, fvmax: torch.Tensor) -> torch.Tensor:
    """``FV(v)``, MuJoCo's force-velocity curve."""
    y = fvmax - 1.0
    lengthening = fvmax - (y - v) * (y - v) / y.clamp_min(MIN_VALUE)
    return torch.where(v <= -1.0, 0.0, torch.where(v <= 0.0, (v + 1.0) * (v + 1.0),
                                                   torch.where(v <= y, lengthening, fvmax)))


def _passive(l: torch.Tensor, lmax: torch.Tensor, fpmax: torch.Tensor) -> torch.Tensor:
    """``FP(l)``, MuJoCo's passive force-length curve, in units of the peak force."""
    b = 0.5 * (1.0 + lmax)
    width = (b - 1.0).clamp_min(MIN_VALUE)
    return torch.where(l <= 1.0, 0.0, torch.where(l <= b, fpmax * _half_parabola((l - 1.0) / width),
                                                  fpmax * (0.5 + (l - b) / width)))


def gains(sys: System, length: torch.Tensor, velocity: torch.Tensor) -> torch.Tensor:
    """``-F0 FL(l) FV(v)`` ``(M, B)`` of the muscle-gain actuators at their lengths and velocities ``(M, B)``."""
    prm = lanes.param(sys.muscle_gain_prm, 1, 1)
    l, v = _normalised(prm, lanes.param(sys.muscle_gain_range, 1, 1), length, velocity)
    return -prm[2] * _active_length(l, prm[4], prm[5]) * _velocity(v, prm[8])


def biases(sys: System, length: torch.Tensor) -> torch.Tensor:
    """``-F0 FP(l)`` ``(M', B)`` of the muscle-bias actuators at their lengths ``(M', B)``."""
    prm = lanes.param(sys.muscle_bias_prm, 1, 1)
    l, _ = _normalised(prm, lanes.param(sys.muscle_bias_range, 1, 1), length, torch.zeros_like(length))
    return -prm[2] * _passive(l, prm[5], prm[7])
