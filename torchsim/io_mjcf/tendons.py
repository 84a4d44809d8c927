"""MuJoCo fixed tendons -> torchsim tendons: ``L = sum_k coef_k q_k`` over hinge and slide dofs, with passive
stiffness (dead band ``lengthspring``) and damping, soft limits, and actuators with tendon transmission.

Spatial tendons, armature, frictionloss, nonlinear (polynomial) stiffness or damping, plasticity and actuator
force limits on a tendon are refused naming the tendon. ``System`` documents the fields.
"""

import mujoco
import numpy as np
import torch

from torchsim.io_mjcf.subset import UnsupportedMJCFError, name


def tendon_fields(m: mujoco.MjModel, jnt_dof: dict) -> dict:
    """The System's tendon fields and ``act_tendon``; ``jnt_dof``: MuJoCo joint id -> torchsim dof."""
    wraps = []  # (tendon, dof, coef)
    for t in range(m.ntendon):
        _check_tendon(m, t, jnt_dof)
        for w in range(m.tendon_adr[t], m.tendon_adr[t] + m.tendon_num[t]):
            wraps.append((t, jnt_dof[m.wrap_objid[w]], m.wrap_prm[w]))
    is_tendon = m.actuator_trntype == int(mujoco.mjtTrn.mjTRN_TENDON)
    limited = m.tendon_limited.astype(bool)
    return dict(
        zip(("ten_wrap_tendon", "ten_wrap_dof", "ten_wrap_coef"), wrap_columns(wraps)),
        ten_stiffness=torch.as_tensor(m.tendon_stiffness.copy()),
        ten_damping=torch.as_tensor(m.tendon_damping.copy()),
        ten_lengthspring=torch.as_tensor(m.tendon_lengthspring.copy()),
        ten_limited=torch.as_tensor(limited), ten_range=torch.as_tensor(m.tendon_range.copy()),
        ten_margin=torch.as_tensor(m.tendon_margin.copy()),
        ten_solimp=torch.as_tensor(m.tendon_solimp_lim.copy()),
        ten_limit_gains=torch.as_tensor(solref_gains(m, m.tendon_solref_lim, m.tendon_solimp_lim)),
        ten_invweight=torch.as_tensor(m.tendon_invweight0.copy()),
        ten_springs=bool(np.any(m.tendon_stiffness != 0) or np.any(m.tendon_damping != 0)),
        ten_limits=bool(limited.any()), act_on_tendons=bool(is_tendon.any()),
        act_tendon=torch.as_tensor(np.where(is_tendon, m.actuator_trnid[:, 0], -1), dtype=torch.long),
    )


def wrap_columns(wraps: list) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Rows ``(W,)``, dofs ``(W,)`` and coefficients ``(W,)`` of ``(row, dof, coef)`` terms: linear combinations
    of dof coordinates (``torchsim.tendons.combine``), a tendon's length or an equality constraint's side."""
    dtypes = (np.int64, np.int64, float)
    return tuple(torch.as_tensor(np.array([w[k] for w in wraps], dtype=d)) for k, d in enumerate(dtypes))


def solref_gains(m: mujoco.MjModel, ref: np.ndarray, solimp: np.ndarray) -> np.ndarray:
    """``(C, 2)``: MuJoCo's ``K``, ``B`` of each constraint's reference acceleration ``-B v - K imp r`` from its
    ``solref (C, 2)`` (``timeconst, dampratio``, or ``-stiffness, -damping``) and ``dmax = solimp[:, 1]``."""
    dmax = solimp[:, 1]
    refsafe = not m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_REFSAFE)
    # MuJoCo keeps the time constant at least 2 timesteps so its own step stays stable
    timeconst = np.maximum(ref[:, 0], 2 * m.opt.timestep) if refsafe else ref[:, 0]
    direct = ref[:, 0] <= 0
    with np.errstate(divide="ignore"):  # np.where evaluates the branch a direct solref does not take
        k = np.where(direct, -ref[:, 0] / dmax**2, 1 / (dmax * timeconst * ref[:, 1]) ** 2)
        b = np.where(direct, -ref[:, 1] / dmax, 2 / (dmax * timeconst))
    return np.stack([k, b], -1).reshape(-1, 2)


def _check_tendon(m: mujoco.MjModel, t: int, jnt_dof: dict) -> None:
    tendon = name(m, mujoco.mjtObj.mjOBJ_TENDON, t)
    wraps = range(m.tendon_adr[t], m.tendon_adr[t] + m.tendon_num[t])
    if any(m.wrap_type[w] != int(mujoco.mjtWrap.mjWRAP_JOINT) for w in wraps):
        raise UnsupportedMJCFError(f"tendon {tendon!r}: spatial tendons are not supported (only <fixed> tendons)")
    if any(m.wrap_objid[w] not in jnt_dof for w in wraps):
        raise UnsupportedMJCFError(f"tendon {tendon!r}: a fixed tendon may only couple hinge and slide joints")
    refused = {
        "armature": m.tendon_armature[t] != 0,
        "frictionloss": m.tendon_frictionloss[t] != 0,  # joint frictionloss on hinges and slides is supported
        "polynomial stiffness/damping": np.any(m.tendon_stiffnesspoly[t] != 0) or np.any(m.tendon_dampingpoly[t] != 0),
        "plasticity (springyield)": m.tendon_springyield[t] != 0 or m.tendon_plasticadr[t] != -1,
        "actuatorfrcrange": m.tendon_actfrclimited[t],
    }
    for feature, present in refused.items():
        if present:
            raise UnsupportedMJCFError(f"tendon {tendon!r}: {feature} is not supported; remove it or set it to 0")
