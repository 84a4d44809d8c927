"""SAC (twin Q, learned temperature, Polyak targets) on a batched torchsim env with an on-device replay buffer.

Each iteration collects ``num_envs x unroll`` steps (uniformly random actions for the first ``random_frames``), adds
them to the buffer and runs ``updates_per_iter`` gradient steps on minibatches of ``batch_size``.
"""

import torch
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.objectives import SACLoss, SoftUpdate

from torchsim.algos.common import EPISODES, Run, RunningEpisodes, maybe_compile
from torchsim.algos.env_factory import make_env, make_eval_env, obs_norm
from torchsim.algos.networks import make_actor, make_value
from torchsim.algos.distributed import Ranks


def train(cfg, out_dir, ranks: Ranks = Ranks()) -> Run:
    if ranks.parallel:  # its many small updates per env step would wait on an all-reduce each
        raise ValueError("algo=sac runs in one process; data-parallel training (torchrun) is for algo=ppo")
    a, device = cfg.algo, torch.device(cfg.device)
    env = make_env(cfg, a.num_envs, device, train=True)
    actor = make_actor(env, a.policy_net, device)
    qvalue = make_value(env, a.q_net, device, with_action=True)
    loss_module = SACLoss(actor, qvalue, num_qvalue_nets=2, loss_function="l2", alpha_init=a.alpha_init)
    loss_module.make_value_estimator(gamma=a.gamma)
    loss_module.set_keys(reward="scaled_reward")  # make_env's RewardScaling writes it beside the task's reward
    target_update = SoftUpdate(loss_module, tau=a.tau)
    # one optimiser suffices: SACLoss detaches what each of its three losses must not train
    optim = torch.optim.Adam(loss_module.parameters(), lr=a.lr)
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(a.buffer_size, device=device), batch_size=a.batch_size)
    eval_env = make_eval_env(cfg, env)
    collector = Collector(env, actor, frames_per_batch=a.num_envs * a.unroll, total_frames=-1, device=device,
                          auto_register_policy_transforms=False,
                          init_random_frames=0 if cfg.resume else a.random_frames)
    # the replay buffer is not checkpointed: a resumed run refills it from its own steps
    run = Run(cfg, out_dir, {"loss": loss_module, "optim": optim, "obs_norm": obs_norm(env),
                             EPISODES: RunningEpisodes(collector, env)}, actor, eval_env=eval_env, train_env=env)
    loss_fn = maybe_compile(loss_module, cfg)
    for data in collector:
        run.record_batch(data)
        buffer.extend(data.reshape(-1))
        for _ in range(a.updates_per_iter):
            minibatch = buffer.sample()
            losses = loss_fn(minibatch)
            loss = losses["loss_actor"] + losses["loss_qvalue"] + losses["loss_alpha"]
            optim.zero_grad()
            loss.backward()
            grad_norm = nn.utils.clip_grad_norm_(loss_module.parameters(), float("inf"))  # measures, never clips
            run.check_update(losses, grad_norm, minibatch)
            optim.step()
            target_update.step()
        run.end_iteration(losses.select("loss_actor", "loss_qvalue", "loss_alpha", "alpha").detach())
        if run.finished():
            break
    collector.shutdown()
    run.finish()
    return run
