"""The recipes' envs: a task's batch (built by its task module, :mod:`torchsim.algos.tasks`) with running observation
normalisation, episode return and length, and for training the scaled reward; the evaluation env beside it."""

import logging

from omegaconf import DictConfig
from torchrl.envs import Compose, RewardSum, StepCounter, TransformedEnv
from torchrl.envs.transforms import RewardScaling

from torchsim.algos import tasks
from torchsim.algos.settings import compiles
from torchsim.algos.normalization import RunningNorm

log = logging.getLogger("torchsim.train")


def make_env(cfg: DictConfig, num_envs: int, device, train: bool = False, like: TransformedEnv | None = None
             ) -> TransformedEnv:
    """The task ``cfg.env.name`` batched over ``num_envs`` (its task module's ``make_base``: for the MJCF tasks,
    ``physics_task``, compiled physics if ``compiles(cfg, "physics")``, or MuJoCo C's if ``cfg.physics ==
    "mujoco"``, staggered first episodes and the captured step for a ``train`` env; for PointNav, ``nav_task``, the
    layouts of ``cfg.env.split`` if ``train``, else of ``cfg.env.eval_split``, and a recurrent policy's state
    transforms) with running observation normalisation (``RunningNorm``, statistics over the batch too, of the keys
    the task names), episode return (``episode_reward``) and length (``step_count``); a ``train`` env also emits
    ``scaled_reward`` (``cfg.algo.reward_scale`` times the reward). ``like``: an env whose stepper (System and
    compiled step) this one shares, for any ``num_envs`` above 1."""
    base, normalised, extra = tasks.for_name(cfg.env.name).make_base(cfg, num_envs, device, train, like=like)
    spec = base.observation_spec
    norm = RunningNorm({k: spec[k].shape[base.batch_dims:] for k in normalised}, decay=cfg.obs_norm_decay,
                       eps=1e-4, dtype=spec[normalised[0]].dtype).to(device)
    transforms = [norm, RewardSum(), StepCounter(), *extra]
    if train:  # the losses learn from scaled_reward; reward (and episode_reward) stay the task's
        transforms.append(RewardScaling(0.0, cfg.algo.reward_scale, in_keys=["reward"], out_keys=["scaled_reward"]))
    return TransformedEnv(base, Compose(*transforms))


def make_eval_env(cfg: DictConfig, train_env: TransformedEnv) -> TransformedEnv:
    """The evaluation env: ``cfg.eval.episodes`` envs sharing ``train_env``'s compiled step. On CPU that step serves
    any batch above one env; on a GPU it is compiled for its batch (the ``loop`` strategy, static shapes), so there
    the evaluation runs on the training batch's size instead of compiling a second graph (measured on an H100: a
    second 43 s compile for 128 envs, none for the training batch)."""
    episodes = cfg.eval.episodes
    if train_env.device.type != "cpu" and compiles(cfg, "physics") and episodes != train_env.batch_size[0]:
        episodes = train_env.batch_size[0]
        log.info(f"evaluating {episodes} episodes (the training batch) on {train_env.device}: the compiled step "
                 f"serves one batch size there")
    like = train_env if tasks.for_env(train_env).SHARES_STEPPER else None
    return make_env(cfg, episodes, train_env.device, like=like)


def obs_norm(env: TransformedEnv) -> RunningNorm:
    return env.transform[0]
