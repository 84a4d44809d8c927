"""torchsim's environment suite: TorchRL ``EnvBase`` envs batched over ``num_envs``, and their MJCF assets.

    env = torchsim.envs.make("ant", num_envs=1024)      # names: torchsim.envs.list()
"""

import builtins
import pathlib

ASSETS_DIR = pathlib.Path(__file__).parent / "assets"


def asset_path(name: str) -> pathlib.Path:
    """Return the path of a bundled asset (e.g. ``"ant.xml"``); raise FileNotFoundError if missing."""
    path = ASSETS_DIR / name
    if not path.is_file():
        available = sorted(p.name for p in ASSETS_DIR.iterdir() if p.is_file()) if ASSETS_DIR.is_dir() else []
        raise FileNotFoundError(f"asset {name!r} not found in {ASSETS_DIR}; available: {available}")
    return path


from torchsim.envs.base import TorchsimEnv  # noqa: E402
from torchsim.envs.locomotion import Ant, HalfCheetah, Hopper, Humanoid, Walker2d  # noqa: E402
from torchsim.envs.manipulation import Pusher, Reacher  # noqa: E402
from torchsim.envs.pendulums import InvertedDoublePendulum, InvertedPendulum  # noqa: E402
from torchsim.envs.targets import Fetch, Grasp  # noqa: E402
from torchsim.envs.ur5e import UR5eReach  # noqa: E402

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
    (``dtype``, ``episode_length``, ``native_autoreset``, ``method``, ``substeps``, ``stagger_episodes``)."""
    if name not in ENVS:
        raise ValueError(f"unknown env {name!r}; available: {', '.join(ENVS)}")
    return ENVS[name](num_envs, device=device, **kwargs)


__all__ = ["ASSETS_DIR", "asset_path", "make", "list", "TorchsimEnv", *(cls.__name__ for cls in ENVS.values())]
