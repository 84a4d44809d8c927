"""The MJCF subset torchsim loads, and the error that names what falls outside it."""

import math
import warnings

import mujoco


class UnsupportedMJCFError(ValueError):
    """The model uses an MJCF feature outside torchsim's supported subset (see ``torchsim.io_mjcf``)."""


def check_supported(m: mujoco.MjModel) -> None:
    """Raise for model-wide elements torchsim cannot simulate; warn for those it ignores harmlessly. Per-body,
    per-actuator and per-geom limits are checked where those are converted."""
    unsupported = {
        "flexcomp/flex": m.nflex, "skin": m.nskin,  # <equality>: io_mjcf.equality
        "mocap body": m.nmocap, "hfield": m.nhfield,
    }
    for element, count in unsupported.items():
        if count:
            raise UnsupportedMJCFError(
                f"<{element}> is not supported by torchsim ({count} found); see torchsim.io_mjcf for the supported subset"
            )
    if m.nsensor:
        warnings.warn(f"{m.nsensor} <sensor> elements are ignored by torchsim", stacklevel=3)


def warn_turning_hinges(m: mujoco.MjModel) -> None:
    """Warn for hinges whose limits or angle-driven forces reach past half a turn.

    A substep measures a hinge's angle from body poses, which fix it only within one turn: in a window around the
    hinge's range, or around its qpos0 if unlimited (``kinematics.dof_angles``; ``State.q`` carries the whole
    turns). The limits, springs and servos of a hinge whose range is wider than a turn act on the angle within one
    turn, and a spring, tendon, equality constraint or position servo on an unlimited hinge sees its angle jump by
    2 pi half a turn from qpos0."""
    coupled = set(m.wrap_objid[m.wrap_type == mujoco.mjtWrap.mjWRAP_JOINT])
    coupled |= {int(m.eq_obj1id[e]) for e in range(m.neq) if m.eq_type[e] == mujoco.mjtEq.mjEQ_JOINT}
    coupled |= {int(m.eq_obj2id[e]) for e in range(m.neq) if m.eq_type[e] == mujoco.mjtEq.mjEQ_JOINT}
    coupled |= {int(m.actuator_trnid[a, 0]) for a in range(m.nu)
                if m.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT and m.actuator_biasprm[a, 1] != 0}
    hinges = [j for j in range(m.njnt) if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE]
    wide = [j for j in hinges if m.jnt_limited[j] and m.jnt_range[j, 1] - m.jnt_range[j, 0] > 2 * math.pi]
    driven = [j for j in hinges if not m.jnt_limited[j] and (m.jnt_stiffness[j] != 0 or j in coupled)]
    for joints, what in ((wide, "have ranges wider than a turn: a substep reads their angles within one turn, and "
                                "their limits, springs and servos act on that angle"),
                         (driven, "are unlimited and drive springs, tendons, equality constraints or position "
                                  "servos, which see the angle jump by 2 pi half a turn from qpos0 (State.q stays "
                                  "continuous)")):
        if joints:
            names = ", ".join(repr(name(m, mujoco.mjtObj.mjOBJ_JOINT, j)) for j in joints)
            warnings.warn(f"hinges {names} {what}", stacklevel=3)


def name(m: mujoco.MjModel, obj, i: int) -> str:
    """The MJCF name of object ``i`` of type ``obj`` (``mujoco.mjtObj``), or ``#i`` for an unnamed one."""
    return mujoco.mj_id2name(m, obj, i) or f"#{i}"
