"""A run's pictures: the learning curves (``curves.png``) and the policy's video (its task module's, from the
recorded trajectory: :mod:`torchsim.algos.tasks`; the MJCF tasks' through :func:`render_gif`)."""

import logging
import pathlib

import numpy as np
from torchrl.envs import TransformedEnv

from torchsim.algos import tasks

log = logging.getLogger("torchsim.train")


def video(env: TransformedEnv, env_name: str, trajectory, path: pathlib.Path) -> None:
    """Write env 0's recorded ``trajectory`` (``evaluate(..., record=True)``) as the GIF ``path``, as its task
    module does: a navigation env's map and depth view (10 frames/s), a physics env's bodies (``render_gif``)."""
    tasks.for_env(env).video(env, env_name, trajectory, path)


def plot_curves(history: dict, path, title: str) -> None:
    """Eval and train return against env steps and against wall-clock minutes, and the training batches' mean reward
    per env step (it moves before whole-episode returns do in short runs); for goal-reaching tasks a fourth panel
    shows the evaluation success rate against env steps (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    goal_task = bool(history.get("eval_success"))
    fig, axes = plt.subplots(1, 4 if goal_task else 3, figsize=(20 if goal_task else 15, 3.8))
    for key, style in (("eval", "o-"), ("train", "-")):
        rows = np.array(history[key]).reshape(-1, 3)
        axes[0].plot(rows[:, 0], rows[:, 2], style, label=f"{key} return")
        axes[1].plot(rows[:, 1] / 60, rows[:, 2], style, label=f"{key} return")
    for ax in axes[:2]:
        ax.set_ylabel("return")
    rows = np.array(history.get("step_reward", [])).reshape(-1, 3)
    axes[2].plot(rows[:, 0], rows[:, 2], "-", color="C2", label="train reward per env step")
    axes[2].set_ylabel("reward per step")
    if goal_task:
        rows = np.array(history["eval_success"])
        axes[3].plot(rows[:, 0], rows[:, 2], "o-", label="eval success rate")
        axes[3].set_ylabel("success rate")
        axes[3].set_ylim(-0.02, 1.02)
    for ax in axes:
        ax.set_xlabel("wall-clock (min)" if ax is axes[1] else "env steps")
        ax.grid(alpha=0.3)
        ax.legend()
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
