"""PPO (clipped objective, GAE) on a batched torchsim env, everything on ``cfg.device``.

Each iteration collects ``num_envs x unroll`` steps with the stochastic policy, computes GAE advantages once (with
the critic of the iteration's start, as CleanRL does), then runs ``epochs`` passes of ``minibatches`` Adam steps
over the batch, drawn without replacement by a TorchRL replay buffer. With a recurrent policy
(``algo.policy_net.lstm``, navigation envs), the buffer's elements are the envs' ``(unroll,)`` sequences, so each
minibatch holds whole sequences that GAE and the loss replay through the LSTM in recurrent mode, from the states
stored at each sequence's first step.
"""

import torch
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.data.replay_buffers import SamplerWithoutReplacement
from torchrl.modules import set_recurrent_mode
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from torchsim.algos.common import EPISODES, MINIBATCH_ORDER, Run, RunningEpisodes, maybe_compile
from torchsim.algos.env_factory import make_env, make_eval_env, obs_norm
from torchsim.algos.nav_policy import is_recurrent
from torchsim.algos.networks import make_actor, make_state_probe, make_value
from torchsim.algos.distributed import Ranks
from torchsim.algos.optim import make_optimizer, make_schedule


class PPO:
    """The pieces of a PPO run: training env, actor, critic, loss, optimiser and collector (``cfg.algo``); with
    several ``ranks`` (``torchrun``), this rank's share of the envs and the reductions that keep the ranks' networks
    equal (``torchsim.algos.distributed``)."""

    def __init__(self, cfg, ranks: Ranks = Ranks()):
        a, device = cfg.algo, ranks.device(cfg.device)
        self.cfg, self.device, self.ranks = cfg, device, ranks
        num_envs = ranks.shard(a.num_envs)
        self.env = make_env(cfg, num_envs, device, train=True)
        self.actor = make_actor(self.env, a.policy_net, device)
        self.critic = make_value(self.env, a.value_net, device, with_action=False, actor=self.actor)
        self.recurrent = is_recurrent(self.actor)
        # several ranks standardise each minibatch's advantages over all of them (_epochs), one the loss does
        self.loss_module = ClipPPOLoss(self.actor, self.critic, clip_epsilon=a.clip_epsilon,
                                       entropy_coeff=a.entropy_coeff, critic_coeff=a.critic_coeff,
                                       normalize_advantage=not ranks.parallel, loss_critic_type="l2")
        # a pixel policy's auxiliary loss (algos.networks.StateProbe): its read-out is trained with the rest
        self.state_probe = make_state_probe(self.actor, self.env, a.get("state_probe_coeff", 0.0), device)
        self.params = [*self.loss_module.parameters(),
                       *(self.state_probe.readout.parameters() if self.state_probe is not None else ())]
        ranks.broadcast_([*self.params, *self.loss_module.buffers()])
        # torch.vmap (GAE's call over the root and next steps) cannot run an LSTM's control flow
        self.gae = GAE(gamma=a.gamma, lmbda=a.gae_lambda, value_network=self.critic, average_gae=False,
                       device=device, deactivate_vmap=self.recurrent)
        self.gae.set_keys(reward="scaled_reward")  # make_env's RewardScaling writes it beside the task's reward
        frames = num_envs * a.unroll
        self.optim = make_optimizer(self.params, a, frames * ranks.world_size)
        self.lr_schedule = make_schedule(self.optim, a, cfg.budget.env_steps, frames * ranks.world_size)
        if self.recurrent and num_envs % a.minibatches:
            raise ValueError(f"algo.minibatches ({a.minibatches}) must divide each rank's envs (num_envs / ranks = "
                             f"{num_envs}) with a recurrent policy: its minibatches are whole per-env sequences")
        if frames % a.minibatches:
            raise ValueError(f"algo.minibatches ({a.minibatches}) must divide each rank's env steps per iteration "
                             f"(num_envs / ranks x unroll = {frames}): every minibatch has the loss graph's shape")
        capture = cfg.get("capture", False)  # the env compiled its step (make_env); the policy, here
        self.collector = Collector(self.env, self.actor, frames_per_batch=frames, total_frames=-1, device=device,
                                   auto_register_policy_transforms=False, compile_policy=capture,
                                   cudagraph_policy=capture and device.type == "cuda")
        # elements: env steps, or with a recurrent policy the envs' (unroll,) sequences
        elements = num_envs if self.recurrent else frames
        self.batches = ReplayBuffer(storage=LazyTensorStorage(elements, device=device),
                                    sampler=SamplerWithoutReplacement(), batch_size=elements // a.minibatches)
        self.loss_fn = maybe_compile(self.loss_module, cfg)
        self.updates = 0
        # what the loss reads once advantages are in; the minibatch buffer holds only these, since sampling indexes
        # every stored leaf
        k = self.loss_module.tensor_keys
        self.loss_inputs = {*self.actor.in_keys, *self.critic.in_keys, k.action, k.sample_log_prob, k.advantage,
                            k.value_target}

    def state(self) -> dict:
        """What a checkpoint holds and a resumed run restores, in that order: the schedule after the optimiser, whose
        rate it sets."""
        state = {"loss": self.loss_module, "optim": self.optim, "obs_norm": obs_norm(self.env)}
        if self.state_probe is not None:
            state["state_probe"] = self.state_probe.readout
        if self.lr_schedule is not None:
            state["lr_schedule"] = self.lr_schedule
        return {**state, EPISODES: RunningEpisodes(self.collector, self.env), MINIBATCH_ORDER: self.batches.sampler}

    def update(self, data, check_update) -> dict:
        """Up to ``epochs`` passes over ``data`` (num_envs, unroll), fewer if an epoch's mean approximate KL from
        the collecting policy exceeds ``target_kl``; ``check_update(losses, grad_norm, minibatch)`` runs before
        every optimiser step. Returns the last minibatch's loss terms, the last epoch's mean KL and the epochs
        run."""
        a = self.cfg.algo
        with torch.no_grad(), set_recurrent_mode(True):  # an LSTM runs over the time dimension (no-op without)
            self.gae(data)
        inputs = data.select(*self.loss_inputs)
        self.batches.extend(inputs if self.recurrent else inputs.reshape(-1))
        # Once the first update has compiled the loss (checking every guard), later ones feed it minibatches of the
        # same shapes, dtypes and modules, so only the guards that tell cached graphs apart need to run: dynamo's
        # full check cost ~0.6 ms of a ~5 ms minibatch step (measured: update 730 -> 590 ms on the main job).
        with torch.compiler.set_stance(skip_guard_eval_unsafe=self.updates > 0):
            losses, kl, epoch = self._epochs(a, check_update)
        self.updates += 1
        lr = self.optim.param_groups[0]["lr"]
        if self.lr_schedule is not None:
            self.lr_schedule.step()
        logged = ["loss_objective", "loss_critic", "loss_entropy"]
        if self.state_probe is not None:
            logged.append("loss_state_probe")
        return {**losses.select(*logged).detach(), "kl_approx": kl, "epochs": epoch, "lr": lr}

    def _epochs(self, a, check_update):
        """The minibatch Adam steps of one update: (last minibatch's losses, last epoch's mean KL, epochs run)."""
        for epoch in range(1, a.epochs + 1):
            kl = []
            for minibatch in self.batches:  # one pass, without replacement
                if self.ranks.parallel:
                    advantage = self.loss_module.tensor_keys.advantage
                    minibatch[advantage] = self.ranks.standardize(minibatch[advantage])
                losses = self.loss_fn(minibatch)
                loss = losses["loss_objective"] + losses["loss_critic"] + losses["loss_entropy"]
                if self.state_probe is not None:
                    losses["loss_state_probe"] = self.state_probe(minibatch["pixels"], minibatch["privileged_state"])
                    loss = loss + a.state_probe_coeff * losses["loss_state_probe"]
                self.optim.zero_grad()
                loss.backward()
                self.ranks.average_grads_(self.params)
                grad_norm = nn.utils.clip_grad_norm_(self.params, a.max_grad_norm or float("inf"))
                check_update(losses, grad_norm, minibatch)
                self.optim.step()
                kl.append(losses["kl_approx"].detach())
            kl = self.ranks.mean(torch.stack(kl).mean())
            if a.target_kl is not None and kl > a.target_kl:
                break
        return losses, kl, epoch


def train(cfg, out_dir, ranks: Ranks = Ranks()) -> Run:
    ppo = PPO(cfg, ranks)
    eval_env = make_eval_env(cfg, ppo.env) if ranks.is_main else None
    run = Run(cfg, out_dir, ppo.state(), ppo.actor, eval_env=eval_env, train_env=ppo.env, ranks=ranks)
    for data in ppo.collector:  # data: (num_envs / ranks, unroll)
        run.record_batch(data)
        losses = ppo.update(data, run.check_update)
        ranks.average_moments_(obs_norm(ppo.env))
        run.end_iteration(losses)
        if ranks.agree(run.finished()):
            break
    ppo.collector.shutdown()
    run.finish()
    return run
