"""Where a trained Pusher policy leaves the object: the reward alone cannot tell an arm that only reaches the
object from one that pushes it to the goal.

    python studies/pusher_outcome.py outputs/ppo_pusher/<run>/checkpoints/last.pt [--episodes 64] [--seed 7]

For each physics (torchsim, and MuJoCo C through ``torchsim.execution.mujoco``) the deterministic policy runs one
episode per env from the same start states (``--seed``); printed: the object's distance to the goal in the table's
plane at the start and after 99 of the episode's 100 actions (the 100th would restart it; medians), the share of
episodes that end with the object within 5 cm of the goal, and the tip's distance to the object.
"""

import argparse

import torch
from omegaconf import OmegaConf
from torchrl.envs import ExplorationType, set_exploration_type

from torchsim.algos.checkpoints import load_checkpoint, load_policy
from torchsim.algos.env_factory import make_env


def distances(env) -> tuple[torch.Tensor, torch.Tensor]:
    """Per env: the object's distance to the goal in the x-y plane [m] and the tip's to the object [m]."""
    base = env.base_env
    tip, obj, goal = base.mj_body_positions(base.state).unbind(1)
    return (obj - goal)[:, :2].norm(dim=-1), (tip - obj).norm(dim=-1)


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("checkpoint")
    p.add_argument("--episodes", type=int, default=64)
    p.add_argument("--seed", type=int, default=7)
    args = p.parse_args()
    ckpt = load_checkpoint(args.checkpoint)
    cfg = OmegaConf.create(ckpt["cfg"])
    if cfg.env.name != "pusher":
        raise SystemExit(f"{args.checkpoint} is a {cfg.env.name} policy, not a pusher one")
    for physics in ("torchsim", "mujoco"):
        cfg.physics = physics
        env = make_env(cfg, args.episodes, "cpu")
        actor = load_policy(ckpt, env, "cpu")
        torch.manual_seed(args.seed)
        td = env.reset()
        goal_start, tip_start = distances(env)
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            for _ in range(cfg.env.episode_length - 1):  # the last step would restart the episode
                td = env.step_mdp(env.step(actor(td)))
        goal_end, tip_end = distances(env)
        print(f"{physics}: object to goal {goal_start.median():.3f} -> {goal_end.median():.3f} m (median), within "
              f"5 cm at the end in {(goal_end < 0.05).float().mean():.0%} of {args.episodes} episodes; tip to "
              f"object {tip_start.median():.3f} -> {tip_end.median():.3f} m")


if __name__ == "__main__":
    main()
