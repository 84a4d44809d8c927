"""The recurrent PointNav policy (``algo.policy_net.lstm``, algos/nav_policy.py): its LSTM state is zeroed at every
episode start and the collector's step-by-step run equals the recurrent replay that PPO learns from; its actions
depend on the past; PPO trains on whole per-env sequences through Hydra and the checkpoint evaluates; a minibatch
count that does not divide the envs fails clearly."""

import pytest
import torch
from torchrl.collectors import Collector
from torchrl.envs import ExplorationType, set_exploration_type
from torchrl.modules import set_recurrent_mode

from test_nav_policy import SMALL
from test_train import config
from torchsim.algos.env_factory import make_env
from torchsim.algos.evaluate import main as evaluate_main
from torchsim.algos.networks import make_actor, make_value
from torchsim.algos.ppo import PPO
from torchsim.algos.train import run

LSTM = ["algo.policy_net.lstm=16", "env.episode_length=5"]  # 5-step episodes: resets inside every sequence


@pytest.fixture(scope="module")
def cfg():
    return config(*SMALL, *LSTM)


def test_collected_steps_equal_the_recurrent_replay_across_resets(cfg):
    """The collector runs the policy one step at a time, carrying the LSTM state through the env; the loss replays
    each env's sequence over the time dimension from its first stored state. Both give the same logits, resets in
    mid-sequence included (there ``is_init`` is set and the stored state is zero)."""
    torch.manual_seed(0)
    env = make_env(cfg, 4, "cpu", train=True)
    actor = make_actor(env, cfg.algo.policy_net, "cpu")
    collector = Collector(env, actor, frames_per_batch=4 * 12, total_frames=-1, auto_register_policy_transforms=False)
    batches = iter(collector)
    next(batches)
    data = next(batches)  # the second batch: its sequences start from a carried, nonzero state
    collector.shutdown()
    is_init = data["is_init"].squeeze(-1)
    assert data.shape == (4, 12) and is_init[:, 1:].any(1).all()
    assert data["recurrent_state_h"][:, 0].abs().sum() > 0
    assert not data["recurrent_state_h"][is_init].any() and not data["recurrent_state_c"][is_init].any()
    with torch.no_grad(), set_recurrent_mode(True):
        replayed = actor(data.select(*actor.in_keys))
    torch.testing.assert_close(replayed["logits"], data["logits"], atol=1e-5, rtol=0)


def test_policy_depends_on_the_past(cfg):
    """The same observation after two different histories gives different logits; a feed-forward policy's don't."""
    torch.manual_seed(0)
    env = make_env(cfg, 4, "cpu", train=True)
    actor = make_actor(env, cfg.algo.policy_net, "cpu")
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        td = start = env.reset()
        first = actor(start.clone())["logits"]
        for _ in range(3):
            td = env.step_mdp(env.step(actor(td)))
        now = td.clone().set("depth", start["depth"]).set("pointgoal", start["pointgoal"])  # the first observation
        assert not now["is_init"].any()
        other_history = now.clone().set("recurrent_state_h", torch.zeros_like(now["recurrent_state_h"]))
        assert (actor(now.clone())["logits"] - actor(other_history)["logits"]).abs().max() > 1e-4
        # a fresh episode's start (zero state) reproduces the first step's logits
        again = now.clone().set("is_init", torch.ones_like(now["is_init"]))
        torch.testing.assert_close(actor(again)["logits"], first)


def test_shared_trunk_and_sequence_minibatches(cfg):
    """The value head reads the policy's trunk (one LSTM, its parameters counted once); each minibatch is whole
    sequences of num_envs / minibatches envs, and the first replays the collecting policy exactly (KL 0)."""
    torch.manual_seed(0)
    ppo = PPO(cfg)
    trunk = ppo.actor.module[0][0]
    assert ppo.critic[0] is trunk
    value = make_value(ppo.env, cfg.algo.value_net, "cpu", with_action=False, actor=ppo.actor)
    assert value[0] is trunk and len(ppo.params) == len({id(p) for p in ppo.params})
    minibatches = []
    ppo.update(next(iter(ppo.collector)), lambda losses, grad_norm, mb: minibatches.append((losses, mb)))
    ppo.collector.shutdown()
    assert [mb.shape for _, mb in minibatches] == [(4, 4)] * (cfg.algo.epochs * cfg.algo.minibatches)
    assert abs(minibatches[0][0]["kl_approx"].item()) < 1e-5


def test_two_ppo_iterations_and_evaluation_through_hydra(tmp_path):
    finished = run(config(*SMALL, "algo.policy_net.lstm=16", "budget.env_steps=64", "logger=csv"), tmp_path)
    assert finished.iteration == 2 and finished.env_steps == 64 and len(finished.history["eval_spl"]) == 2
    result = evaluate_main([f"checkpoint={tmp_path / 'checkpoints' / 'last.pt'}", "episodes=2", "max_steps=6",
                            "seed=0"])
    assert result["env"] == "pointnav" and 0 <= result["success_rate"] <= 1 and 0 <= result["spl"] <= 1


def test_minibatches_must_divide_the_envs():
    with pytest.raises(ValueError, match=r"minibatches \(3\) must divide each rank's envs"):
        PPO(config(*SMALL, "algo.policy_net.lstm=16", "algo.minibatches=3", "algo.unroll=3"))
