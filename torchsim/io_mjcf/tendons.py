"""MuJoCo tendons -> torchsim tendons. Fixed tendons: ``L = sum_k coef_k q_k`` over hinge and slide dofs. Spatial
tendons: paths through sites, in branches split by ``<pulley divisor>`` (``torchsim.tendon_paths``). Both with
passive stiffness (dead band ``lengthspring``) and damping, soft limits (a spatial tendon's with MuJoCo's ``a0``
term), actuators with tendon transmission, and dry friction (``frictionloss``) on fixed tendons over hinges.

Wrapping around geoms, sites on mocap bodies, equality constraints on spatial tendons, armature, frictionloss on
spatial tendons or on fixed tendons over slides, nonlinear (polynomial) stiffness or damping, plasticity and
actuator force limits on a tendon are refused naming the tendon. ``System`` documents the fields.
"""

import mujoco
import numpy as np
import torch

from torchsim.io_mjcf.bodies import FusedBodies, compose
from torchsim.io_mjcf.subset import UnsupportedMJCFError, name

_JOINT, _SITE, _PULLEY = (int(w) for w in (mujoco.mjtWrap.mjWRAP_JOINT, mujoco.mjtWrap.mjWRAP_SITE,
                                           mujoco.mjtWrap.mjWRAP_PULLEY))
_HINGE = int(mujoco.mjtJoint.mjJNT_HINGE)


def tendon_fields(m: mujoco.MjModel, jnt_dof: dict, fused: FusedBodies) -> dict:
    """The System's tendon fields and ``act_tendon``; ``jnt_dof``: MuJoCo joint id -> torchsim dof; ``fused``: the
    bodies the sites are fused into."""
    wraps, segments = [], []  # wraps: (tendon, dof, coef); segments: (tendon, (site, site), 1 / divisor)
    for t in range(m.ntendon):
        _check_tendon(m, t, jnt_dof)
        adr = range(m.tendon_adr[t], m.tendon_adr[t] + m.tendon_num[t])
        if m.wrap_type[adr[0]] == _JOINT:
            wraps += [(t, jnt_dof[m.wrap_objid[w]], m.wrap_prm[w]) for w in adr]
        else:
            segments += _segments(m, t, adr)
    frictional = [t for t in range(m.ntendon) if m.tendon_frictionloss[t] != 0]
    friction_terms = [(slot, dof, coef) for slot, t in enumerate(frictional) for row, dof, coef in wraps if row == t]
    ends = [[_site_on_body(m, fused, seg[1][k]) for seg in segments] for k in range(2)]
    spatial = np.array([m.wrap_type[m.tendon_adr[t]] != _JOINT for t in range(m.ntendon)], dtype=bool)
    is_tendon = m.actuator_trntype == int(mujoco.mjtTrn.mjTRN_TENDON)
    limited = m.tendon_limited.astype(bool)
    return dict(
        zip(("ten_wrap_tendon", "ten_wrap_dof", "ten_wrap_coef"), wrap_columns(wraps)),
        ten_seg_tendon=torch.as_tensor([seg[0] for seg in segments], dtype=torch.long),
        ten_seg_body=torch.as_tensor([[body for body, _ in end] for end in ends], dtype=torch.long).reshape(2, -1),
        ten_seg_pos=torch.as_tensor(np.array([[pos for _, pos in end] for end in ends])).reshape(2, -1, 3),
        ten_seg_scale=torch.as_tensor([seg[2] for seg in segments], dtype=torch.float64),
        ten_is_spatial=torch.as_tensor(spatial), ten_spatial=bool(segments),
        ten_stiffness=torch.as_tensor(m.tendon_stiffness.copy()),
        ten_damping=torch.as_tensor(m.tendon_damping.copy()),
        ten_lengthspring=torch.as_tensor(m.tendon_lengthspring.copy()),
        ten_limited=torch.as_tensor(limited), ten_range=torch.as_tensor(m.tendon_range.copy()),
        ten_margin=torch.as_tensor(m.tendon_margin.copy()),
        ten_solimp=torch.as_tensor(m.tendon_solimp_lim.copy()),
        ten_limit_gains=torch.as_tensor(solref_gains(m, m.tendon_solref_lim, m.tendon_solimp_lim)),
        ten_invweight=torch.as_tensor(m.tendon_invweight0.copy()),
        ten_springs=bool(np.any(m.tendon_stiffness != 0) or np.any(m.tendon_damping != 0)),
        ten_limits=bool((limited & ~spatial).any()), ten_path_limits=bool((limited & spatial).any()),
        act_on_tendons=bool(is_tendon.any()),
        ten_frictionloss=torch.as_tensor(m.tendon_frictionloss.copy()),
        ten_friction=torch.as_tensor(frictional, dtype=torch.long),
        **dict(zip(("ten_friction_row", "ten_friction_dof", "ten_friction_coef"), wrap_columns(friction_terms))),
        act_tendon=torch.as_tensor(np.where(is_tendon, m.actuator_trnid[:, 0], -1), dtype=torch.long),
    )


def _segments(m: mujoco.MjModel, t: int, adr: range) -> list:
    """Spatial tendon ``t``'s straight segments ``(t, (site, site), 1 / divisor)``: each pair of consecutive
    sites, as MuJoCo's ``mj_tendon`` takes them; a pulley ends a branch and divides the next ones' lengths by its
    ``divisor``."""
    out, divisor = [], 1.0
    for first, second in zip(adr[:-1], adr[1:]):
        if m.wrap_type[first] == _PULLEY:
            divisor = m.wrap_prm[first]
        if _PULLEY not in (m.wrap_type[first], m.wrap_type[second]):
            out.append((t, (m.wrap_objid[first], m.wrap_objid[second]), 1.0 / divisor))
    return out


def _site_on_body(m: mujoco.MjModel, fused: FusedBodies, site: int) -> tuple[int, np.ndarray]:
    """Site ``site``'s ext body and its position from that body's COM in the body's frame [m] (the world's frame
    and origin for a site on the world)."""
    mj_body = m.site_bodyid[site]
    pos, _ = compose(*fused.frame[mj_body], m.site_pos[site], m.site_quat[site])
    return fused.body_of(m, mj_body), pos - fused.com_of(m, mj_body)


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
    if m.wrap_type[wraps[0]] == _JOINT:
        if any(m.wrap_objid[w] not in jnt_dof for w in wraps):
            raise UnsupportedMJCFError(f"tendon {tendon!r}: a fixed tendon may only couple hinge and slide joints")
        # the dry friction joins the hinges' dof solve (joint_space); slides are solved one dof at a time
        if m.tendon_frictionloss[t] != 0 and any(m.jnt_type[m.wrap_objid[w]] != _HINGE for w in wraps):
            raise UnsupportedMJCFError(f"tendon {tendon!r}: frictionloss on a fixed tendon over slide joints is not "
                                       "supported (only over hinges)")
    else:
        _check_spatial(m, tendon, wraps)
        if m.tendon_frictionloss[t] != 0:
            raise UnsupportedMJCFError(f"tendon {tendon!r}: frictionloss on a spatial tendon is not supported (only "
                                       "on fixed tendons)")
        if any(m.eq_type[e] == int(mujoco.mjtEq.mjEQ_TENDON) and t in (m.eq_obj1id[e], m.eq_obj2id[e])
               for e in range(m.neq)):
            raise UnsupportedMJCFError(f"tendon {tendon!r}: equality constraints on spatial tendons are not "
                                       "supported (only on fixed tendons)")
    refused = {
        "armature": m.tendon_armature[t] != 0,
        "polynomial stiffness/damping": np.any(m.tendon_stiffnesspoly[t] != 0) or np.any(m.tendon_dampingpoly[t] != 0),
        "plasticity (springyield)": m.tendon_springyield[t] != 0 or m.tendon_plasticadr[t] != -1,
        "actuatorfrcrange": m.tendon_actfrclimited[t],
    }
    for feature, present in refused.items():
        if present:
            raise UnsupportedMJCFError(f"tendon {tendon!r}: {feature} is not supported; remove it or set it to 0")


def _check_spatial(m: mujoco.MjModel, tendon: str, wraps: range) -> None:
    """Refuse what a spatial tendon's path may hold beyond sites and pulleys, naming it."""
    for w in wraps:
        if m.wrap_type[w] not in (_SITE, _PULLEY):
            geom = name(m, mujoco.mjtObj.mjOBJ_GEOM, m.wrap_objid[w])
            raise UnsupportedMJCFError(f"tendon {tendon!r}: wrapping around geom {geom!r} is not supported (only "
                                       "sites and pulleys)")
        if m.wrap_type[w] == _SITE and m.body_mocapid[m.body_weldid[m.site_bodyid[m.wrap_objid[w]]]] >= 0:
            site = name(m, mujoco.mjtObj.mjOBJ_SITE, m.wrap_objid[w])
            raise UnsupportedMJCFError(f"tendon {tendon!r}: site {site!r} is on a mocap body, which tendons do not "
                                       "follow in torchsim")
