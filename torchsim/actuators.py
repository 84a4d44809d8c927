"""Controls and passive joint springs -> generalized forces on hinge/slide dofs, with MuJoCo's semantics."""

import torch

from torchsim import lanes
from torchsim.system import System


def dof_forces(sys: System, q: torch.Tensor, qd: torch.Tensor, ctrl: torch.Tensor) -> torch.Tensor:
    """Generalized force ``(D, B)`` on every dof for dof coordinates ``q``/``qd (D, B)`` and ``ctrl (U, B)``.

    Actuator force ``gain * ctrl + b0 + b1 * gear * q + b2 * gear * qd``, with ``ctrl`` clamped to ``ctrlrange`` and
    the force to ``forcerange`` where limited, enters the dof as ``gear * force`` (MuJoCo joint transmission).
    Joint springs add ``-stiffness * (q - springref)``.
    """
    lo, hi = lanes.param(sys.act_ctrl_range, 2).unbind(-2)
    ctrl = torch.where(lanes.param(sys.act_ctrl_limited, 1), torch.minimum(torch.maximum(ctrl, lo), hi), ctrl)
    q_act, qd_act = q.index_select(-2, sys.act_dof), qd.index_select(-2, sys.act_dof)
    b0, b1, b2 = lanes.param(sys.act_bias, 2).unbind(-2)
    gear = lanes.param(sys.act_gear, 1)
    force = lanes.param(sys.act_gain, 1) * ctrl + b0 + b1 * gear * q_act + b2 * gear * qd_act
    f_lo, f_hi = lanes.param(sys.act_force_range, 2).unbind(-2)
    force = torch.where(lanes.param(sys.act_force_limited, 1), torch.minimum(torch.maximum(force, f_lo), f_hi), force)
    spring = -lanes.param(sys.dof_stiffness, 1) * (q - lanes.param(sys.dof_springref, 1))
    return spring.index_add(-2, sys.act_dof, gear * force)
