"""MuJoCo actuators -> torchsim actuators: joint, tendon or site transmission, fixed or muscle gain, no, affine or
muscle bias, and activation dynamics (``dyntype`` integrator, filter, filterexact, muscle: MuJoCo allows these one
activation state each, ``actdim`` 1)."""

import mujoco
import numpy as np
import torch

from torchsim.activation import ACTIVATION_KINDS
from torchsim.io_mjcf.bodies import FusedBodies, compose
from torchsim.io_mjcf.subset import UnsupportedMJCFError, name

_JOINT, _TENDON, _SITE, _BODY = (int(t) for t in (mujoco.mjtTrn.mjTRN_JOINT, mujoco.mjtTrn.mjTRN_TENDON,
                                                  mujoco.mjtTrn.mjTRN_SITE, mujoco.mjtTrn.mjTRN_BODY))
_MUSCLE_GAIN, _MUSCLE_BIAS = int(mujoco.mjtGain.mjGAIN_MUSCLE), int(mujoco.mjtBias.mjBIAS_MUSCLE)
_DYNTYPES = {int(getattr(mujoco.mjtDyn, f"mjDYN_{kind.upper()}")): k for k, kind in enumerate(ACTIVATION_KINDS)}


def actuator_fields(m: mujoco.MjModel, jnt_dof: dict, fused: FusedBodies) -> dict:
    """The System's actuator, activation and site transmission fields; ``jnt_dof``: MuJoCo joint id -> torchsim dof
    of the hinges and slides; ``fused``: the bodies the sites are fused into."""
    for i in range(m.nu):
        _check_actuator(m, i, jnt_dof)
    activated = [i for i in range(m.nu) if m.actuator_dyntype[i] != int(mujoco.mjtDyn.mjDYN_NONE)]
    on_site = [i for i in range(m.nu) if m.actuator_trntype[i] == _SITE]
    ends = [[_site_frame(m, fused, m.actuator_trnid[i, k]) for i in on_site] for k in range(2)]
    kinds = [_DYNTYPES[m.actuator_dyntype[i]] for i in activated]
    gain_muscles = [i for i in range(m.nu) if m.actuator_gaintype[i] == _MUSCLE_GAIN]
    bias_muscles = [i for i in range(m.nu) if m.actuator_biastype[i] == _MUSCLE_BIAS]
    return dict(
        act_dof=torch.as_tensor([jnt_dof[m.actuator_trnid[i, 0]] if m.actuator_trntype[i] == _JOINT else -1
                                 for i in range(m.nu)], dtype=torch.long),
        act_gear=torch.as_tensor(m.actuator_gear[:, 0].copy()),
        act_gain=torch.as_tensor(np.where(m.actuator_gaintype == _MUSCLE_GAIN, 0.0, m.actuator_gainprm[:, 0])),
        act_bias=torch.as_tensor(np.where((m.actuator_biastype == _MUSCLE_BIAS)[:, None], 0.0,
                                          m.actuator_biasprm[:, :3])),
        act_ctrl_range=torch.as_tensor(m.actuator_ctrlrange.copy()),
        act_ctrl_limited=torch.as_tensor(m.actuator_ctrllimited.astype(bool)),
        act_force_range=torch.as_tensor(m.actuator_forcerange.copy()),
        act_force_limited=torch.as_tensor(m.actuator_forcelimited.astype(bool)),
        act_adr=torch.as_tensor(m.actuator_actadr.copy(), dtype=torch.long),
        activation_actuator=torch.as_tensor(activated, dtype=torch.long),
        activation_kind=torch.as_tensor(kinds, dtype=torch.long),
        activation_dynprm=torch.as_tensor(m.actuator_dynprm[activated, :3].reshape(-1, 3)),
        activation_range=torch.as_tensor(m.actuator_actrange[activated].reshape(-1, 2)),
        activation_limited=torch.as_tensor(m.actuator_actlimited[activated].astype(bool)),
        activation_early=torch.as_tensor(m.actuator_actearly[activated].astype(bool)),
        activation_kinds=tuple(ACTIVATION_KINDS[k] for k in sorted(set(kinds))),
        muscle_gain_actuator=torch.as_tensor(gain_muscles, dtype=torch.long),
        muscle_gain_prm=torch.as_tensor(_muscle_prm(m, m.actuator_gainprm, gain_muscles)),
        muscle_gain_range=torch.as_tensor(m.actuator_lengthrange[gain_muscles].reshape(-1, 2)),
        muscle_bias_actuator=torch.as_tensor(bias_muscles, dtype=torch.long),
        muscle_bias_prm=torch.as_tensor(_muscle_prm(m, m.actuator_biasprm, bias_muscles)),
        muscle_bias_range=torch.as_tensor(m.actuator_lengthrange[bias_muscles].reshape(-1, 2)),
        act_muscles=bool(gain_muscles or bias_muscles),
        site_act_actuator=torch.as_tensor(on_site, dtype=torch.long),
        site_act_body=torch.as_tensor([[body for body, _, _ in end] for end in ends], dtype=torch.long).reshape(2, -1),
        site_act_pos=torch.as_tensor(np.array([[pos for _, pos, _ in end] for end in ends])).reshape(2, -1, 3),
        site_act_quat=torch.as_tensor(np.array([[quat for _, _, quat in end] for end in ends])).reshape(2, -1, 4),
        site_act_gear=torch.as_tensor(m.actuator_gear[on_site].reshape(-1, 6)),
        site_act_has_ref=torch.as_tensor(m.actuator_trnid[on_site, 1].reshape(-1) >= 0),
        act_on_sites=bool(on_site),
    )


def _check_actuator(m: mujoco.MjModel, i: int, jnt_dof: dict) -> None:
    actuator = name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, i)
    trntype = m.actuator_trntype[i]
    if trntype == _BODY:
        raise UnsupportedMJCFError(f"actuator {actuator!r}: body transmission (adhesion) is not supported")
    if not ((trntype == _JOINT and m.actuator_trnid[i, 0] in jnt_dof) or trntype in (_TENDON, _SITE)):
        raise UnsupportedMJCFError(f"actuator {actuator!r}: only joint transmission to a hinge or slide, tendon or "
                                   "site transmission is supported")  # tendons: io_mjcf.tendons
    if m.actuator_dyntype[i] not in _DYNTYPES and m.actuator_dyntype[i] != int(mujoco.mjtDyn.mjDYN_NONE):
        raise UnsupportedMJCFError(f"actuator {actuator!r}: only the activation dynamics (dyntype) none, "
                                   f"{', '.join(ACTIVATION_KINDS)} are supported")
    if m.actuator_gaintype[i] not in (int(mujoco.mjtGain.mjGAIN_FIXED), _MUSCLE_GAIN) or m.actuator_biastype[i] not in (
            int(mujoco.mjtBias.mjBIAS_NONE), int(mujoco.mjtBias.mjBIAS_AFFINE), _MUSCLE_BIAS):
        raise UnsupportedMJCFError(f"actuator {actuator!r}: only fixed or muscle gain and none, affine or muscle bias "
                                   "are supported")


def _muscle_prm(m: mujoco.MjModel, prm: np.ndarray, rows: list) -> np.ndarray:
    """The muscle parameters ``prm[rows, :9]`` with each peak force resolved: a negative one is MuJoCo's
    ``scale / acc0`` (``prm[3]`` over the actuator's acceleration at unit force in ``qpos0``)."""
    out = prm[rows, :9].reshape(-1, 9).copy()
    out[:, 2] = np.where(out[:, 2] < 0, out[:, 3] / np.maximum(m.actuator_acc0[rows], mujoco.mjMINVAL), out[:, 2])
    return out


def _site_frame(m: mujoco.MjModel, fused: FusedBodies, site: int) -> tuple[int, np.ndarray, np.ndarray]:
    """Site ``site``'s ext body, its position from that body's COM and its orientation in the body's frame; the
    world's origin for ``-1`` (a site actuator without a refsite)."""
    if site < 0:
        return len(fused.roots), np.zeros(3), np.array([1.0, 0, 0, 0])
    mj_body = m.site_bodyid[site]
    pos, quat = compose(*fused.frame[mj_body], m.site_pos[site], m.site_quat[site])
    return fused.body_of(m, mj_body), pos - fused.com_of(m, mj_body), quat
