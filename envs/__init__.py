"""torchsim's environment suite: TorchRL ``EnvBase`` envs batched over ``num_envs``, and their MJCF assets.

    env = torchsim.envs.make("ant", num_envs=1024)      # names: torchsim.envs.list(), list("physics"), ...
"""

import builtins

from torchsim.envs.base import ASSETS_DIR, TorchsimEnv, asset_path
from torchsim.envs.fetch_reach import FetchReach
from torchsim.envs.locomotion import Ant, HalfCheetah, Hopper, Humanoid, Walker2d
from torchsim.envs.manipulation import Pusher, Reacher
from torchsim.envs.nav import PointNav
from torchsim.envs.pendulums import InvertedDoublePendulum, InvertedPendulum
from torchsim.envs.pixels import pendulum_strip
from torchsim.envs.targets import Fetch, Grasp
from torchsim.envs.ur5e import UR5eReach

ENVS = {
    "ant": Ant, "halfcheetah": HalfCheetah, "humanoid": Humanoid, "reacher": Reacher, "hopper": Hopper,
    "walker2d": Walker2d, "inverted_pendulum": InvertedPendulum,
    "inverted_double_pendulum": InvertedDoublePendulum, "pusher": Pusher, "ur5e_reach": UR5eReach,
    "grasp": Grasp, "fetch": Fetch,
}

#: Pixel versions of tasks (``torchsim.envs.pixels``): name -> (task, default keyword arguments); :func:`make`'s
#: keyword arguments override these.
#: ``inverted_pendulum_pixels`` also emits the full state as ``privileged_state``, which its recipe's critic reads
#: instead of the images (the policy sees the images and the proprioception only).
PIXEL_ENVS = {
    # top-down RGB 48x48; the policy gets the arm's angles and rates, the target only through the image
    "reacher_pixels": ("reacher", dict(from_pixels=True, pixel_size=48, pixel_state="proprio",
                                       render_compile=True)),
    # depth 48x48 from a camera riding on the cart, 4 stacked frames (120 ms: the pole's rate, docs/training_pixels.md);
    # the policy gets the cart's position and velocity, the pole's angle and rate only through the images
    "inverted_pendulum_pixels": ("inverted_pendulum", dict(from_pixels=True, pixel_size=48, pixel_state="proprio",
                                                           frame_stack=4, render_compile=True,
                                                           pixel_privileged_state=True)),
    # the same through a 24x96 strip across the pole (0.63 cm per pixel instead of 1.9)
    "inverted_pendulum_pixels_strip": ("inverted_pendulum", dict(
        from_pixels=True, cameras=pendulum_strip, pixel_size=(24, 96), pixel_state="proprio", frame_stack=2,
        render_compile=True)),
}

#: Navigation tasks (``torchsim.envs.nav``): kinematic agents in procedural layouts, not physics models (``kwargs``
#: to the class).
NAV_ENVS = {"pointnav": PointNav}


#: Physics tasks on third-party robot models, loaded from their packages (``pip install -e '.[robotics]'``), not
#: bundled: gymnasium-robotics' FetchReach (``torchsim.envs.fetch_reach``).
ROBOTICS_ENVS = {"fetch_reach": FetchReach}

#: The kinds of env :func:`list` names.
KINDS = {"physics": ENVS, "pixels": PIXEL_ENVS, "navigation": NAV_ENVS, "robotics": ROBOTICS_ENVS}


def list(kind: str = "all") -> builtins.list[str]:  # noqa: A001 - the public name asked for: torchsim.envs.list()
    """Names :func:`make` builds: every one, or those of one ``kind`` (``"physics"``: the MJCF tasks;
    ``"pixels"``: physics tasks observed through cameras; ``"navigation"``)."""
    if kind != "all" and kind not in KINDS:
        raise ValueError(f"unknown kind of env {kind!r}; expected 'all' or one of {builtins.list(KINDS)}")
    return [name for k, names in KINDS.items() if kind in ("all", k) for name in names]


def make(name: str, num_envs: int = 1, device="cpu", **kwargs) -> TorchsimEnv:
    """Build env ``name`` with ``batch_size=(num_envs,)`` on ``device``; ``kwargs`` go to the env class
    (``dtype``, ``episode_length``, ``native_autoreset``, ``method``, ``substeps``, ``stagger_episodes``, ``stepper``,
    and the pixel options ``from_pixels``, ``cameras``, ``pixel_size``, ``pixel_kind``, ``pixel_state``,
    ``frame_stack``, ``render_compile``, ``pixel_supersample``, ``pixel_privileged_state``: :class:`TorchsimEnv`).
    ``name`` may also be one of :data:`PIXEL_ENVS` or :data:`NAV_ENVS`."""
    if name in NAV_ENVS:
        return NAV_ENVS[name](num_envs, device=device, **kwargs)
    if name in ROBOTICS_ENVS:
        return ROBOTICS_ENVS[name](num_envs, device=device, **kwargs)
    if name in PIXEL_ENVS:
        task, defaults = PIXEL_ENVS[name]
        return ENVS[task](num_envs, device=device, **{**defaults, **kwargs})
    if name not in ENVS:
        available = [*ENVS, *PIXEL_ENVS, *NAV_ENVS, *ROBOTICS_ENVS]
        raise ValueError(f"unknown env {name!r}; available: {', '.join(available)}")
    return ENVS[name](num_envs, device=device, **kwargs)


__all__ = ["ASSETS_DIR", "asset_path", "make", "list", "TorchsimEnv", *(cls.__name__ for cls in ENVS.values()),
           "FetchReach"]
