"""The MJCF tasks' part of the recipes (``torchsim.envs``: physics models, their pixel versions too), as
:mod:`torchsim.algos.tasks` asks of a task: the env batch from the config (physics ``torchsim`` compiled or eager,
or ``mujoco``; the physics options ``contact_model``, ``method``, ``substeps``; staggered first episodes and the
captured step for training), joint positions as the recorded trajectory and a rendered GIF as the video."""

import pathlib

import torch
from omegaconf import DictConfig

import torchsim.envs
from torchsim.algos import env_factory  # its compiles(); env_factory imports this module through tasks
from torchsim.execution.mujoco import MujocoStepper

#: The env names this module serves: every other one (:mod:`torchsim.algos.tasks` asks it last).
NAMES = None

#: No metrics beside the return and, for goal tasks, the final ``goal_distance``.
EPISODE_END_METRICS = ()

#: An evaluation env shares the training env's stepper (System and compiled step).
SHARES_STEPPER = True


def matches(env) -> bool:
    return True


def make_base(cfg: DictConfig, num_envs: int, device, train: bool, like=None):
    """The task's batch for ``cfg`` (``like``: an env whose stepper it shares), and the observation keys the
    running normaliser standardises; no further transforms."""
    physics = cfg.get("physics", "torchsim")  # checkpoints from before the key ran on torchsim
    contact_model = cfg.get("contact_model")
    method, substeps = cfg.get("method"), cfg.get("substeps")  # None: the task's (and in checkpoints before the keys)
    if physics not in ("torchsim", "mujoco"):
        raise ValueError(f"physics must be 'torchsim' or 'mujoco', got {physics!r}")
    if like is not None:
        stepper = like.base_env.stepper
    elif physics == "mujoco":
        probe = torchsim.envs.make(cfg.env.name, device=device, contact_model=contact_model)  # System, MuJoCo model
        stepper = MujocoStepper(probe.base_sys, probe.mj_model)
    else:
        stepper = "auto" if env_factory.compiles(cfg, "physics") else "eager"
    base = torchsim.envs.make(cfg.env.name, num_envs=num_envs, device=device, episode_length=cfg.env.episode_length,
                              stagger_episodes=train and cfg.stagger_episodes, stepper=stepper,
                              **(dict(contact_model=contact_model, method=method, substeps=substeps)
                                 if isinstance(stepper, str) else {}))
    if train and cfg.get("capture", False):
        if stepper != "auto":  # traced as a graph, the reference step compiles for minutes
            raise ValueError("capture=true compiles the env's step around the engine's compiled step: it needs "
                             "compile=true (or compile_physics=true) and physics=torchsim")
        base.compile_step(mode="reduce-overhead" if torch.device(device).type == "cuda" else None)
    return base, [k for k in ("observation", "privileged_state") if k in base.observation_spec.keys()], []


def reseed(env, seed: int) -> None:
    """Nothing: the start states come from torch's generator, which a seeded evaluation forks and seeds."""


def snapshot(env, row: int = 0) -> torch.Tensor:
    """Env ``row``'s joint positions ``q``."""
    return env.base_env.state.q[row].cpu()


def trajectory(snapshots: list):
    return torch.stack(snapshots).double().numpy()


def video(env, env_name: str, trajectory, path: pathlib.Path) -> None:
    """The recorded joint positions rendered as a GIF (``render_gif``)."""
    from torchsim.algos.outputs import render_gif

    render_gif(env_name, trajectory, env.base_env.dt, path)
