"""MuJoCo actuators -> torchsim actuators: joint or tendon transmission, fixed gain, no or affine bias, no
activation."""

import mujoco
import torch

from torchsim.io_mjcf.subset import UnsupportedMJCFError, name


def actuator_fields(m: mujoco.MjModel, jnt_dof: dict) -> dict:
    """The System's actuator fields; ``jnt_dof``: MuJoCo joint id -> torchsim dof of the hinges and slides."""
    for i in range(m.nu):
        actuator = name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, i)
        joint = m.actuator_trntype[i] == int(mujoco.mjtTrn.mjTRN_JOINT) and m.actuator_trnid[i, 0] in jnt_dof
        if not (joint or m.actuator_trntype[i] == int(mujoco.mjtTrn.mjTRN_TENDON)):  # tendons: io_mjcf.tendons
            raise UnsupportedMJCFError(f"actuator {actuator!r}: only joint transmission to a hinge or slide, or "
                                       "tendon transmission, is supported")
        if m.actuator_dyntype[i] != int(mujoco.mjtDyn.mjDYN_NONE):
            raise UnsupportedMJCFError(f"actuator {actuator!r}: activation dynamics (dyntype) are not supported")
        if m.actuator_gaintype[i] != int(mujoco.mjtGain.mjGAIN_FIXED) or m.actuator_biastype[i] not in (
                int(mujoco.mjtBias.mjBIAS_NONE), int(mujoco.mjtBias.mjBIAS_AFFINE)):
            raise UnsupportedMJCFError(f"actuator {actuator!r}: only fixed gain and none/affine bias are supported")
    return dict(
        act_dof=torch.as_tensor([-1 if m.actuator_trntype[i] == int(mujoco.mjtTrn.mjTRN_TENDON)
                                 else jnt_dof[m.actuator_trnid[i, 0]] for i in range(m.nu)], dtype=torch.long),
        act_gear=torch.as_tensor(m.actuator_gear[:, 0].copy()),
        act_gain=torch.as_tensor(m.actuator_gainprm[:, 0].copy()),
        act_bias=torch.as_tensor(m.actuator_biasprm[:, :3].copy()),
        act_ctrl_range=torch.as_tensor(m.actuator_ctrlrange.copy()),
        act_ctrl_limited=torch.as_tensor(m.actuator_ctrllimited.astype(bool)),
        act_force_range=torch.as_tensor(m.actuator_forcerange.copy()),
        act_force_limited=torch.as_tensor(m.actuator_forcelimited.astype(bool)),
    )
