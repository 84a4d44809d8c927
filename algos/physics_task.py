"""The MJCF tasks' part of the recipes (``torchsim.envs``: physics models, their pixel versions too), as
:mod:`torchsim.algos.tasks` asks of a task: the env batch from the config (physics ``torchsim`` compiled or eager,
or ``mujoco``; the physics options ``contact_model``, ``method``, ``substeps``; staggered first episodes and the
captured step for training), joint positions as the recorded trajectory and a rendered GIF as the video."""

import logging
import os
import pathlib
import subprocess
import sys
import warnings

import numpy as np
import torch
from omegaconf import DictConfig

import torchsim.envs
from torchsim.algos.settings import compiles
from torchsim.execution.mujoco import MujocoStepper

log = logging.getLogger("torchsim.train")

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
        stepper = MujocoStepper(probe.base_sys, probe.mj_model, substeps=cfg.get("mujoco_substeps", 1))
    else:
        stepper = "auto" if compiles(cfg, "physics") else "eager"
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
    """The recorded joint positions rendered as a GIF (:func:`render_gif`)."""
    render_gif(env_name, trajectory, env.base_env.dt, path)


def render_gif(env_name: str, qpos: np.ndarray, dt: float, path: pathlib.Path, renderer: str = "torchsim",
               width: int = 320, height: int = 240) -> None:
    """Write a ``width`` x ``height`` GIF of ``qpos``. ``renderer="torchsim"`` (default): torchsim's own renderer,
    in this process (no GL context; ``torchsim.envs.video.render_frames_torchsim``); models it cannot draw (height
    fields) fall back to ``"mujoco"``: MuJoCo's renderer in a child process, as MuJoCo picks its GL backend when first
    imported (``MUJOCO_GL``), which in this process happened before we could choose EGL."""
    path = pathlib.Path(path)
    if renderer == "torchsim":
        from torchsim.envs.video import render_frames_torchsim, save_gif
        from torchsim.render import UnsupportedGeomError

        task = torchsim.envs.make(env_name)
        try:
            save_gif(render_frames_torchsim(task.mj_model, task.sys, qpos, width, height), path, fps=1.0 / dt)
            log.info(f"video: {path}")
            return
        except UnsupportedGeomError as err:
            log.info(f"torchsim's renderer cannot draw {env_name} ({err}); rendering with MuJoCo")
    np.save(path.with_suffix(".npy"), qpos)
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    proc = subprocess.run([sys.executable, "-m", "torchsim.algos.render", env_name, str(path.with_suffix(".npy")),
                           str(path), str(1.0 / dt), str(width), str(height)], env=env, capture_output=True, text=True)
    if proc.returncode:
        warnings.warn(f"no video ({proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else 'render failed'})")
    else:
        log.info(f"video: {path}")
