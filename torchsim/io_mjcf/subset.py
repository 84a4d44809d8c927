"""The MJCF subset torchsim loads, and the error that names what falls outside it."""

import warnings

import mujoco


class UnsupportedMJCFError(ValueError):
    """The model uses an MJCF feature outside torchsim's supported subset (see ``torchsim.io_mjcf``)."""


def check_supported(m: mujoco.MjModel) -> None:
    """Raise for model-wide elements torchsim cannot simulate; warn for those it ignores harmlessly. Per-body,
    per-actuator and per-geom limits are checked where those are converted."""
    unsupported = {
        "flexcomp/flex": m.nflex,  # <equality>: io_mjcf.equality; mocap bodies: io_mjcf.bodies
    }
    for element, count in unsupported.items():
        if count:
            raise UnsupportedMJCFError(
                f"<{element}> is not supported by torchsim ({count} found); see torchsim.io_mjcf for the supported subset"
            )
    if m.nskin:  # a skin is drawn over the bodies: no physics to lose
        warnings.warn(f"{m.nskin} <skin> elements are ignored by torchsim (a skin has no physics)", stacklevel=3)


def name(m: mujoco.MjModel, obj, i: int) -> str:
    """The MJCF name of object ``i`` of type ``obj`` (``mujoco.mjtObj``), or ``#i`` for an unnamed one."""
    return mujoco.mj_id2name(m, obj, i) or f"#{i}"
