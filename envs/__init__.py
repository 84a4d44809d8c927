"""torchsim's environment suite: TorchRL ``EnvBase`` envs batched over ``num_envs``, and their MJCF assets.

    env = torchsim.envs.make("ant", num_envs=1024)      # names: torchsim.envs.list()
"""

import builtins

from torchsim.envs.base import ASSETS_DIR, TorchsimEnv, asset_path
from torchsim.envs.locomotion import Ant, HalfCheetah, Hopper, Humanoid, Walker2d
from torchsim.envs.manipulation import Pusher, Reacher
from torchsim.envs.pendulums import InvertedDoublePendulum, InvertedPendulum
from torchsim.envs.targets import Fetch, Grasp
from torchsim.envs.ur5e import UR5eReach

ENVS = {
    "ant": Ant, "halfcheetah": HalfCheetah, "humanoid": Humanoid, "reacher": Reacher, "hopper": Hopper,
    "walker2d": Walker2d, "inverted_pendulum": InvertedPendulum,
    "inverted_double_pendulum": InvertedDoublePendulum, "pusher": Pusher, "ur5e_reach": UR5eReach,
    "grasp": Grasp, "fetch": Fetch,
}


def list() -> builtins.list[str]:  # noqa: A001 - the public name asked for: torchsim.envs.list()
    """Names accepted by :func:`make`."""
    return builtins.list(ENVS)


def make(name: str, num_envs: int = 1, device="cpu", **kwargs) -> TorchsimEnv:
    """Build env ``name`` with ``batch_size=(num_envs,)`` on ``device``; ``kwargs`` go to the env class
    (``dtype``, ``episode_length``, ``native_autoreset``, ``method``, ``substeps``, ``stagger_episodes``, ``stepper``)."""
    if name not in ENVS:
        raise ValueError(f"unknown env {name!r}; available: {', '.join(ENVS)}")
    return ENVS[name](num_envs, device=device, **kwargs)


__all__ = ["ASSETS_DIR", "asset_path", "make", "list", "TorchsimEnv", *(cls.__name__ for cls in ENVS.values())]
