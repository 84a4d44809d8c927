"""PointNav's part of the recipes (``torchsim.envs.nav``: a kinematic agent in procedural layouts, no physics), as
:mod:`torchsim.algos.tasks` asks of a task: its env batch from the config (episodes drawn from the layouts of
``cfg.env.split`` for training, ``cfg.env.eval_split`` for evaluation; depth normalised per pixel; for a recurrent
policy, ``cfg.algo.policy_net.lstm``, the transforms holding its states), its episode-end metrics (``success``,
``spl``), reseeding for seeded evaluations, the recorded frames and the video (map from above beside the depth
view). Its networks are in :mod:`torchsim.algos.nav_policy`."""

import logging
import pathlib

from omegaconf import DictConfig

import torchsim.envs
from torchsim.algos import nav_policy
from torchsim.envs.nav import video as nav_video

log = logging.getLogger("torchsim.train")

#: The env names this module serves.
NAMES = tuple(torchsim.envs.NAV_ENVS)

#: Per-env values the env emits on an episode's last step only (zero before): an evaluation sums them per episode.
EPISODE_END_METRICS = ("success", "spl")

#: An evaluation env builds its own env (no compiled physics step to share with the training batch's).
SHARES_STEPPER = False


def matches(env) -> bool:
    """Whether ``env`` (a TorchRL env, transformed or not) is a navigation task."""
    return nav_policy.is_nav_env(env)


def make_base(cfg: DictConfig, num_envs: int, device, train: bool, like=None):
    """The PointNav batch for ``cfg``, the observation keys the running normaliser standardises (depth, per pixel)
    and the transforms a recurrent policy needs (``nav_policy.recurrent_transforms``; none otherwise)."""
    base = torchsim.envs.make(cfg.env.name, num_envs=num_envs, device=device, episode_length=cfg.env.episode_length,
                              num_layouts=cfg.env.num_layouts, split=cfg.env.split if train else cfg.env.eval_split,
                              seed=cfg.seed)
    return base, ["depth"], nav_policy.recurrent_transforms(cfg.algo.policy_net)


def reseed(env, seed: int) -> None:
    """A seeded evaluation: the env draws its episodes (layouts, starts, goals) from its own generator."""
    env.set_seed(seed)


def snapshot(env, row: int = 0):
    """Env ``row``'s frame for the video (``torchsim.envs.nav.video.NavFrame``)."""
    return nav_video.snapshot(env.base_env, row)


def trajectory(snapshots: list):
    return snapshots


def video(env, env_name: str, trajectory, path: pathlib.Path) -> None:
    """The recorded frames as a GIF at 10 frames/s."""
    from torchsim.envs.video import save_gif

    save_gif(nav_video.episode_frames(trajectory), path, fps=10)
    log.info(f"video: {path}")
