"""Analytic policy gradients (algos/apg.py): the loss's gradient is the derivative of the truncated return, a few
Adam steps on it reduce it, the evaluated actor is the policy APG trains, and the recipe runs through Hydra."""

import pytest
import torch
from hydra import compose, initialize_config_dir
from tensordict.nn import NormalParamExtractor
from torch import nn
from torchrl.envs import Compose, ExplorationType, RewardSum, StepCounter, TransformedEnv, set_exploration_type

import torchsim.envs
from torchsim.algos.apg import Rollout, policy_net
from torchsim.algos.env_factory import make_env
from torchsim.algos.normalization import RunningNorm
from torchsim.algos.networks import make_actor
from torchsim.algos.distributed import Ranks
from torchsim.algos.train import CONFIG_DIR, RECIPES, run
from torchsim.envs.pendulums import InvertedPendulum

QUIET = ["video.enabled=false", "logger=''", "compile=false", "threads=1"]


class UprightPendulum(InvertedPendulum):
    """The inverted pendulum with a smooth reward (its own, 1 per step, has no gradient): keep the pole upright
    and the cart at the centre. It never terminates, so no fresh (random) start enters a finite difference."""

    def _terminated(self, state):
        return torch.zeros_like(state.diverged)

    def _reward(self, before, after, ctrl):
        return -(after.q[:, 1] ** 2) - 0.1 * after.q[:, 0] ** 2 - 0.01 * after.qd[:, 1] ** 2


def config(*overrides):
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


def wrapped(base) -> TransformedEnv:
    """``base`` with ``make_env``'s transforms (the recipe reads the normaliser and the base env)."""
    spec = base.observation_spec["observation"]
    norm = RunningNorm({"observation": spec.shape[base.batch_dims:]}, eps=1e-4, dtype=spec.dtype)
    return TransformedEnv(base, Compose(norm, RewardSum(), StepCounter()))


def small_policy(obs_dim: int, act_dim: int, dtype) -> nn.Module:
    return nn.Sequential(nn.Linear(obs_dim, 8, dtype=dtype), nn.Tanh(), nn.Linear(8, 2 * act_dim, dtype=dtype),
                         NormalParamExtractor())


def restart(rollout: Rollout, saved) -> None:
    """Put the rollout back at the saved state (start, task, counters, observation)."""
    base = rollout.base
    base.state, base.task, rollout.obs = saved[0], saved[1], saved[3]
    base.step_count.copy_(saved[2])


def snapshot(rollout: Rollout):
    base = rollout.base
    return base.state, base.task, base.step_count.clone(), rollout.obs


def test_loss_gradient_matches_finite_difference():
    """float64, 4 envs of the upright pendulum (5-step horizon) and of the reacher (3 steps of 40 substeps): d loss /
    d theta along a random parameter direction equals the central difference of the unroll's loss (normaliser
    statistics fixed). The difference's own error falls as eps^2 (reacher, seed 0: 5.1e-3, 5.1e-5, 4.8e-7 relative
    at eps 1e-5, 1e-6, 1e-7, then rounding: 4.1e-7 at 1e-8), so eps is 1e-7. Measured there over seeds 0-2: reacher
    4.8e-7, 3.4e-8, 4.8e-10 relative; pendulum <= 2.3e-10; hence 1e-5 and 1e-6."""
    torch.manual_seed(0)
    for task, horizon, rel in ((UprightPendulum(4, dtype=torch.float64), 5, 1e-6),
                               (torchsim.envs.make("reacher", 4, dtype=torch.float64), 3, 1e-5)):
        env = wrapped(task)
        rollout = Rollout(env, gamma=0.9)
        obs_dim, act_dim = task.observation_size, task.sys.nu
        net = small_policy(obs_dim, act_dim, torch.float64)
        saved = snapshot(rollout)
        rollout.normalise(saved[3], update=True)  # statistics from the start states, then held
        loss, _ = rollout.unroll(net, horizon, update_norm=False)
        params = list(net.parameters())
        grads = torch.autograd.grad(loss, params)
        direction = [torch.randn_like(p) for p in params]
        analytic = sum((g * d).sum() for g, d in zip(grads, direction)).item()
        eps, values = 1e-7, []
        for sign in (1.0, -1.0):
            with torch.no_grad():
                for p, d in zip(params, direction):
                    p.add_(sign * eps * d)
            restart(rollout, saved)
            with torch.no_grad():
                values.append(rollout.unroll(net, horizon, update_norm=False)[0].item())
                for p, d in zip(params, direction):
                    p.sub_(sign * eps * d)
        numeric = (values[0] - values[1]) / (2 * eps)
        assert abs(analytic) > 1e-6, type(task).__name__  # the policy's parameters move the return
        assert analytic == pytest.approx(numeric, rel=rel, abs=1e-9), type(task).__name__


def test_adam_steps_on_the_loss_reduce_it():
    """From the same 8 starts, 3 Adam steps on a 4-step unroll's loss (the recipe's update) lower it by over half
    (measured: 3.8e-2 -> 8.4e-3 -> 3.7e-3)."""
    torch.manual_seed(1)
    env = wrapped(UprightPendulum(8, dtype=torch.float32))
    rollout = Rollout(env)
    net = small_policy(4, 1, torch.float32)
    optim = torch.optim.Adam(net.parameters(), lr=3e-2)
    saved = snapshot(rollout)
    rollout.normalise(saved[3], update=True)
    losses = []
    for _ in range(4):
        restart(rollout, saved)
        loss, record = rollout.unroll(net, 4, update_norm=False)
        losses.append(loss.item())
        optim.zero_grad()
        loss.backward()
        optim.step()
    assert record["next", "reward"].shape == (8, 4, 1)
    assert losses[-1] < 0.5 * losses[0], losses


def test_evaluated_actor_is_the_trained_policy():
    """``evaluate`` runs the actor deterministically: its action is the tanh of the loc APG differentiates."""
    cfg = config("algo=apg", "env=reacher", *QUIET)
    env = make_env(cfg, 4, "cpu")
    actor = make_actor(env, cfg.algo.policy_net, "cpu")
    rollout = Rollout(env)
    td = env.reset()  # the evaluation's normalised observation
    base = env.base_env
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        evaluated = actor(td)["action"]
        trained = rollout.action(policy_net(actor), base._observation(base.state, base._zero_ctrl()), update=False)
    torch.testing.assert_close(evaluated, trained)


def test_recipe_runs_through_hydra(tmp_path):
    """``algo=apg`` trains, evaluates and checkpoints like the other recipes; a reward without a gradient and
    several ranks are refused with a clear error."""
    cfg = config("algo=apg", "env=reacher", "algo.num_envs=4", "algo.horizon=3", "budget.env_steps=24",
                 "eval.episodes=2", "eval.max_steps=4", *QUIET)
    trained = run(cfg, tmp_path)
    assert trained.env_steps == 24 and trained.iteration == 2
    assert len(trained.history["eval"]) == 2 and len(trained.history["eval_success"]) == 2
    assert (tmp_path / "checkpoints" / "last.pt").exists() and (tmp_path / "summary.json").exists()
    with pytest.raises(ValueError, match="no gradient"):
        run(config("algo=apg", "env=inverted_pendulum", "algo.num_envs=2", "algo.horizon=2", "budget.env_steps=4",
                   *QUIET), tmp_path / "pendulum")
    with pytest.raises(ValueError, match="one process"):
        RECIPES["apg"](cfg, tmp_path, Ranks(0, 2))
