"""Controls and passive joint springs -> generalized forces on hinge/slide dofs, with MuJoCo's semantics."""

import torch

from torchsim.system import System


def dof_forces(sys: System, q: torch.Tensor, qd: torch.Tensor, ctrl: torch.Tensor) -> torch.Tensor:
    """Generalized force ``(B, D)`` on every dof for dof coordinates ``q``/``qd (B, D)`` and ``ctrl (B, nu)``.

    Actuator force ``gain * ctrl + b0 + b1 * gear * q + b2 * gear * qd``, with ``ctrl`` clamped to ``ctrlrange`` and
    the force to ``forcerange`` where limited, enters the dof as ``gear * force`` (MuJoCo joint transmission).
    Joint springs add ``-stiffness * (q - springref)``.
    """
    lo, hi = sys.act_ctrl_range.unbind(-1)
    ctrl = torch.where(sys.act_ctrl_limited, torch.minimum(torch.maximum(ctrl, lo), hi), ctrl)
    q_act, qd_act = q.index_select(1, sys.act_dof), qd.index_select(1, sys.act_dof)
    bias = sys.act_bias
    force = (sys.act_gain * ctrl + bias[..., 0] + bias[..., 1] * sys.act_gear * q_act
             + bias[..., 2] * sys.act_gear * qd_act)
    f_lo, f_hi = sys.act_force_range.unbind(-1)
    force = torch.where(sys.act_force_limited, torch.minimum(torch.maximum(force, f_lo), f_hi), force)
    spring = -sys.dof_stiffness * (q - sys.dof_springref)
    return spring.index_add(1, sys.act_dof, sys.act_gear * force)
