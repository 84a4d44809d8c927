"""Evaluation of a policy: each env's first episode, deterministic by default, with what its task module
(:mod:`torchsim.algos.tasks`) adds: episode-end metrics, reseeding, the recorded trajectory."""

from typing import NamedTuple

import numpy as np
import torch
from torchrl.envs import ExplorationType, TransformedEnv, set_exploration_type

from torchsim.algos import tasks


class Evaluation(NamedTuple):
    """Per env (B,): the return and length of its first episode, and, for goal-reaching tasks, the goal distance
    [m] at the episode's end (else None); ``trajectory``: env 0's episode when recorded (else None), as ``q``
    rows ``(T, nq)`` for physics envs and :class:`~torchsim.envs.nav.video.NavFrame` s for navigation envs; for
    navigation tasks (which emit them), the episode's ``success`` (bool) and ``spl``."""

    ret: torch.Tensor
    length: torch.Tensor
    final_distance: torch.Tensor | None
    trajectory: np.ndarray | list | None
    success: torch.Tensor | None = None
    spl: torch.Tensor | None = None

    def success_rate(self, success_distance: float) -> float:
        return (self.final_distance < success_distance).float().mean().item()


@torch.no_grad()
def evaluate(env: TransformedEnv, policy, max_steps: int, record: bool = False, seed: int | None = None,
             deterministic: bool = True) -> Evaluation:
    """Deterministic evaluation (or, not ``deterministic``, with sampled actions) of each env's first episode (at
    most ``max_steps`` steps); with ``record``, env 0's trajectory for a video (``video``). Finished envs keep stepping,
    masked out, so the batch stays fixed; the loop stops once every env has finished. With ``seed``, the episodes
    start from the same states at every call (drawn from a forked RNG, leaving the caller's stream alone), so
    successive evaluations compare policies, not start draws; a navigation env draws its episodes from its own
    generator, which ``seed`` then reseeds."""
    task = tasks.for_env(env)
    if seed is None:
        td = env.reset()
    else:
        with torch.random.fork_rng(devices=[env.device] if env.device.type == "cuda" else []):
            torch.manual_seed(seed)
            task.reseed(env, seed)
            td = env.reset()
    alive = torch.ones(env.batch_size, dtype=torch.bool, device=env.device)
    ret = torch.zeros(env.batch_size, device=env.device)
    length = torch.zeros(env.batch_size, dtype=torch.long, device=env.device)
    goal_task = "goal_distance" in env.observation_spec.keys()
    distance = torch.full(env.batch_size, float("nan"), device=env.device) if goal_task else None
    ends = {k: torch.zeros(env.batch_size, device=env.device) for k in task.EPISODE_END_METRICS}
    trajectory = [task.snapshot(env, 0)] if record else None
    with set_exploration_type(ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM):
        for t in range(max_steps):
            td = env.step(policy(td))
            ret += td["next", "reward"].squeeze(-1) * alive
            length += alive
            if goal_task:
                distance = torch.where(alive, td["next", "goal_distance"].squeeze(-1), distance)
            for k in ends:  # nonzero on an episode's last step only
                ends[k] += td["next", k].squeeze(-1) * alive
            if record and bool(alive[0]):
                trajectory.append(task.snapshot(env, 0))
            alive &= ~td["next", "done"].squeeze(-1)
            if t % 10 == 9 and not alive.any():  # one host sync every 10 steps
                break
            td = env.step_mdp(td)
    if record:
        trajectory = task.trajectory(trajectory)
    success = ends["success"].bool() if "success" in ends else None
    return Evaluation(ret, length, distance, trajectory, success, ends.get("spl"))
