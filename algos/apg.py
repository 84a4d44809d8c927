"""Analytic policy gradients (APG): a deterministic policy trained by back-propagating through the simulator.

Each iteration rolls the batch ``num_envs`` envs forward ``horizon`` steps with the deterministic policy
``tanh(loc(observation))`` (the mean of ``make_actor``'s tanh-Gaussian, so checkpoints, evaluation and
``torchsim.evaluate`` treat it like a PPO or SAC actor), recording the eager reference step (``torchsim.step``), and
takes one Adam step on the loss ``-reward_scale * mean_(envs, t) gamma^t r_t``: the negative (discounted, per step)
return of the unroll, differentiated through every physics substep, the observation normalisation and the rewards.
The state is carried detached from one unroll to the next (truncated back-propagation); envs that end inside an
unroll restart from fresh states, which carry no gradient. Gradients are clipped to ``max_grad_norm``.

The rollout is written here against the env's pieces (``_ctrl``, ``_advance``: the physics, reward, termination
and task of one step; ``_restart``, ``_observation``), not through ``env.step``: TorchRL's step path updates the
normaliser and the episode counters in place and returns a TensorDict per step, which autograd need not see, and the
task functions are plain differentiable torch. Those functions are the env's own, so the loss is the return of the
same task.

A reward that is constant while an episode runs (the pendulums' 1 per step until they fall) has zero gradient:
APG needs a reward that varies smoothly with the state (a distance, a velocity).
"""

import torch
from tensordict import TensorDict
from torch import nn

from torchsim.algos.common import EPISODES, Run
from torchsim.algos.env_factory import make_env, make_eval_env, obs_norm
from torchsim.algos.networks import make_actor
from torchsim.algos.distributed import Ranks


def policy_net(actor) -> nn.Module:
    """The module mapping normalised ``observation`` to ``(loc, scale)`` inside ``make_actor``'s actor."""
    return actor.module[0].module


class Rollout:
    """A differentiable unroll of ``env`` (a ``make_env`` env) under a deterministic policy; carries the batch's
    state, task, step counters and episode returns (all detached) between unrolls."""

    def __init__(self, env, gamma: float = 1.0):
        self.env, self.base, self.norm, self.gamma = env, env.base_env, obs_norm(env), gamma
        env.reset()  # fresh (or staggered) episodes, and the normaliser's statistics initialised
        b = self.base
        self.obs = b._observation(b.state, b._zero_ctrl())
        self.episode_return = torch.zeros(b.batch_size, dtype=b.sys.dtype, device=b.device)

    def state_dict(self) -> dict:
        """The carried episodes, for a checkpoint: observation, returns so far and the env's state."""
        return {"obs": self.obs, "episode_return": self.episode_return, "env": self.base.episode_state()}

    def load_state_dict(self, state: dict) -> None:
        self.obs, self.episode_return = state["obs"], state["episode_return"]
        self.base.load_episode_state(state["env"])

    def normalise(self, obs: torch.Tensor, update: bool) -> torch.Tensor:
        """``obs`` normalised with the running statistics (after adding it to them, if ``update``); differentiable
        in ``obs``, the statistics held constant."""
        if update:
            self.norm.update("observation", obs.detach())
        return self.norm.normalize("observation", obs)

    def action(self, net: nn.Module, obs: torch.Tensor, update: bool = True) -> torch.Tensor:
        loc, _ = net(self.normalise(obs, update))
        return torch.tanh(loc)

    def unroll(self, net: nn.Module, horizon: int, update_norm: bool = True) -> tuple[torch.Tensor, TensorDict]:
        """Step ``horizon`` times from the carried state; return the loss ``-mean gamma^t r_t`` (with its graph)
        and the batch's record (``next``: reward, done, episode_reward; shape ``(B, horizon)``) for ``Run``."""
        b = self.base
        state, task, obs, steps = b.state, b.task, self.obs, b.step_count.clone()
        total, rewards, dones, returns = 0.0, [], [], []
        for t in range(horizon):
            b.state, b.task = state, task  # the task functions read the current state and task from the env
            action = self.action(net, obs, update_norm)
            ctrl = b._ctrl(action)
            state, task, reward, terminated, truncated, steps = b._advance(state, task, ctrl, steps)
            done = terminated | truncated
            total = total + self.gamma ** t * reward
            self.episode_return = self.episode_return + reward.detach()
            rewards.append(reward.detach())
            dones.append(done)
            returns.append(self.episode_return)
            self.episode_return = torch.where(done, 0.0, self.episode_return)
            # finished envs restart: their fresh states and tasks carry no gradient
            if bool(done.any()):  # one host sync per step; most steps end no episode
                state, task, steps, ctrl = b._restart(done, state, task, steps, ctrl)
            b.state, b.task = state, task
            obs = b._observation(state, ctrl)
        # stop-gradient between unrolls: the next one starts from these values, detached
        b.state = type(state)(*(x.detach() for x in state))
        b.task, self.obs = task.detach(), obs.detach()
        b.step_count.copy_(steps)
        record = TensorDict(next=TensorDict(reward=torch.stack(rewards, 1)[..., None],
                                            done=torch.stack(dones, 1)[..., None],
                                            episode_reward=torch.stack(returns, 1)[..., None]),
                            batch_size=[b.batch_size[0], horizon])
        return -total.mean() / horizon, record


def train(cfg, out_dir, ranks: Ranks = Ranks()) -> Run:
    if ranks.parallel:  # one differentiable unroll per update; nothing here to share between processes
        raise ValueError("algo=apg runs in one process; data-parallel training (torchrun) is for algo=ppo")
    a, device = cfg.algo, torch.device(cfg.device)
    env = make_env(cfg, a.num_envs, device, train=True)
    actor = make_actor(env, a.policy_net, device)
    net = policy_net(actor)
    optim = torch.optim.Adam(actor.parameters(), lr=a.lr)
    eval_env = make_eval_env(cfg, env)
    rollout = Rollout(env, gamma=a.gamma)
    run = Run(cfg, out_dir, {"actor": actor, "optim": optim, "obs_norm": obs_norm(env), EPISODES: rollout}, actor,
              eval_env=eval_env, train_env=env)
    max_norm = float("inf") if a.max_grad_norm is None else a.max_grad_norm
    while not run.finished():
        loss, record = rollout.unroll(net, a.horizon)
        if not loss.requires_grad:
            raise ValueError(f"algo=apg: {cfg.env.name}'s reward does not depend on the actions through the physics "
                             "(e.g. a constant reward per step until the episode ends), so its return has no gradient")
        loss = a.reward_scale * loss
        optim.zero_grad()
        loss.backward()
        grad_norm = nn.utils.clip_grad_norm_(actor.parameters(), max_norm)
        run.record_batch(record)
        run.check_update({"loss": loss.detach()}, grad_norm, record)
        optim.step()
        run.end_iteration({"loss": loss.detach(), "grad_norm": grad_norm})
    run.finish()
    return run
