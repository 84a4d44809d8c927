"""PPO (clipped objective, GAE) on a batched torchsim env, everything on ``cfg.device``.

Each iteration collects ``num_envs x unroll`` steps with the stochastic policy, then runs ``epochs`` passes of
``minibatches`` Adam steps over the batch, recomputing GAE before each pass (the critic moves between passes).
"""

import torch
from torch import nn
from torchrl.collectors import Collector
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from torchsim.algos.common import Run, make_actor, make_env, make_value, maybe_compile, obs_norm


def train(cfg, out_dir) -> Run:
    a, device = cfg.algo, torch.device(cfg.device)
    env = make_env(cfg, a.num_envs, device, train=True)
    actor = make_actor(env, a.policy_net, device)
    critic = make_value(env, a.value_net, device, with_action=False)
    loss_module = ClipPPOLoss(actor, critic, clip_epsilon=a.clip_epsilon, entropy_coeff=a.entropy_coeff,
                              critic_coeff=a.critic_coeff, normalize_advantage=True, loss_critic_type="l2")
    gae = GAE(gamma=a.gamma, lmbda=a.gae_lambda, value_network=critic, average_gae=False, device=device)
    optim = torch.optim.Adam(loss_module.parameters(), lr=a.lr, eps=1e-5)
    run = Run(cfg, out_dir, {"loss": loss_module, "optim": optim, "obs_norm": obs_norm(env)}, actor,
              eval_env=make_env(cfg, cfg.eval.episodes, device), train_env=env)
    collector = Collector(env, actor, frames_per_batch=a.num_envs * a.unroll, total_frames=-1, device=device,
                          auto_register_policy_transforms=False)
    loss_fn = maybe_compile(loss_module, cfg)
    for data in collector:  # data: (num_envs, unroll)
        run.record_batch(data)
        data["next", "reward"] = data["next", "reward"] * a.reward_scale
        for _ in range(a.epochs):
            with torch.no_grad():
                gae(data)
            flat = data.reshape(-1)
            for idx in torch.randperm(flat.numel(), device=device).split(flat.numel() // a.minibatches):
                minibatch = flat[idx]
                losses = loss_fn(minibatch)
                loss = losses["loss_objective"] + losses["loss_critic"] + losses["loss_entropy"]
                optim.zero_grad()
                loss.backward()
                grad_norm = nn.utils.clip_grad_norm_(loss_module.parameters(), a.max_grad_norm)
                run.check_update(losses, grad_norm, minibatch)
                optim.step()
        run.end_iteration(losses.select("loss_objective", "loss_critic", "loss_entropy").detach())
        if run.finished():
            break
    collector.shutdown()
    run.finish()
    return run
