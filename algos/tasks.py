"""What the recipes do differently per kind of task, each kind in a module of its own: :mod:`nav_task` (PointNav)
and :mod:`physics_task` (every MJCF task, the default). Each offers ``NAMES``, ``matches(env)``,
``make_base(cfg, num_envs, device, train, like)`` (the env batch, the keys to normalise, extra transforms),
``SHARES_STEPPER`` (an evaluation env shares the training env's compiled step), ``EPISODE_END_METRICS``,
``reseed(env, seed)``, ``snapshot(env, row)``, ``trajectory(snapshots)`` and ``video(env, env_name, trajectory,
path)``; ``env_factory``, ``evaluation`` and ``outputs`` ask :func:`for_name` or :func:`for_env` which applies."""

from torchsim.algos import nav_task, physics_task

#: The task modules with names of their own, asked in order; :mod:`physics_task` serves every other env.
SPECIAL = (nav_task,)


def for_name(env_name: str):
    """The task module for env ``env_name``."""
    return next((task for task in SPECIAL if env_name in task.NAMES), physics_task)


def for_env(env):
    """The task module for ``env`` (a TorchRL env, transformed or not)."""
    return next((task for task in SPECIAL if task.matches(env)), physics_task)
