"""Training recipes: PPO and SAC learn inverted_pendulum (random play falls within ~10 steps), checkpoints round-trip,
every recipe runs through Hydra overrides, and a diverging run stops naming its step."""

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from hydra import compose, initialize_config_dir
from torchrl.envs import ExplorationType, set_exploration_type
from torchrl.envs.transforms import VecNormV2
from torchrl.envs.utils import RandomPolicy

from torchsim.algos.checkpoints import load_policy
from torchsim.algos.common import TrainingDiverged
from torchsim.algos.env_factory import make_env
from torchsim.algos.evaluation import evaluate
from torchsim.algos.normalization import RunningNorm
from torchsim.algos.networks import make_actor
from torchsim.algos.train import CONFIG_DIR, run

# Eager physics and one thread: these tests check the recipes, not the compiled step (tests/test_training_compile.py)
QUIET = ["video.enabled=false", "logger=''", "compile=false", "threads=1"]
TINY = {"ppo": ["algo.num_envs=8", "algo.unroll=2", "algo.minibatches=2"],
        "sac": ["algo.num_envs=8", "algo.unroll=2", "algo.random_frames=8", "algo.batch_size=8", "algo.updates_per_iter=2"]}


def config(*overrides):
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


def tiny(algo, *overrides):
    """Two iterations of 16 env steps."""
    return config(f"algo={algo}", "env=inverted_pendulum", *TINY[algo], "budget.env_steps=32", "eval.episodes=2",
                  "eval.max_steps=5", *QUIET, *overrides)


# Budgets in env steps, not minutes, so a slow or shared machine does the same work (and gets the same result) as
# an idle one. Seed 0 reaches the limit at 45,056 (PPO, 50-step episodes) and 4,160 (SAC, 100-step episodes) env
# steps (SAC at its first evaluation); the budgets leave 2x (PPO) and 4x (SAC) margin. SAC's episodes are 100
# steps, not 200: as far from random play (5.5) and the untrained policy (26), in half the time.
# PPO's batch is set here (256 envs x 16 steps, 4 epochs x 8 minibatches, as the eager recipes ran) rather than
# taken from the tuned config, which is sized for the compiled engine's 2048 envs.
SMALL_PPO = ["algo.num_envs=256", "algo.unroll=16", "algo.epochs=4", "algo.minibatches=8", "obs_norm_decay=1.0",
             "algo.lr=3e-4", "algo.anneal_lr=false", "eval.episodes=256", "eval.max_steps=${env.episode_length}",
             "eval.at_start=true"]


@pytest.mark.parametrize("algo, limit, env_steps", [("ppo", 50, 90_112), ("sac", 100, 16_384)])
@pytest.mark.timeout(600)
def test_solves_inverted_pendulum(algo, limit, env_steps, tmp_path):
    """Deterministic eval episodes reach the episode limit, where random play and the untrained policy fall.

    Runs stop as soon as evaluation reaches the limit: PPO 48 s, SAC 31 s on one core of a 2-core machine."""
    cfg = config(f"algo={algo}", "env=inverted_pendulum", f"env.episode_length={limit}", "budget.minutes=null",
                 f"budget.env_steps={env_steps}", f"budget.eval_return={limit}", "eval.interval_steps=4096", *QUIET,
                 *(SMALL_PPO if algo == "ppo" else ["eval.episodes=${algo.num_envs}"]))
    trained = run(cfg, tmp_path)
    random_return = evaluate(trained.eval_env, RandomPolicy(trained.eval_env.action_spec), limit).ret
    untrained_return = trained.history["eval"][0][2]
    final = trained.history["eval"][-1][2]
    print(f"{algo}: random {random_return.mean():.1f}, untrained {untrained_return:.1f}, trained {final:.1f} "
          f"after {trained.env_steps} env steps, {trained.wall:.0f} s")
    assert random_return.mean() < 0.2 * limit
    assert final >= 0.95 * limit > untrained_return


def test_checkpoint_round_trip_and_resume(tmp_path):
    trained = run(tiny("ppo"), tmp_path)
    ckpt = torch.load(tmp_path / "checkpoints" / "last.pt", weights_only=True)
    env = make_env(tiny("ppo"), 2, "cpu")
    actor = load_policy(ckpt, env, "cpu")
    for (name, a), b in zip(trained.actor.state_dict().items(), actor.state_dict().values()):
        assert torch.equal(a, b), name
    trained.sync_eval_norm()
    torch.manual_seed(1)
    ret_a = evaluate(trained.eval_env, trained.actor, 5).ret
    obs = trained.eval_env.reset()
    torch.manual_seed(1)
    ret_b = evaluate(env, actor, 5).ret
    assert torch.equal(ret_a, ret_b)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        assert torch.equal(trained.actor(obs.clone())["action"], actor(obs.clone())["action"])
    rng = torch.get_rng_state()  # seeded evaluations start from the same states, off the caller's RNG stream
    runs = [evaluate(env, actor, 5, record=True, seed=seed).trajectory for seed in (3, 3, 4)]
    assert np.array_equal(runs[0], runs[1]) and not np.array_equal(runs[0], runs[2])
    assert torch.equal(torch.get_rng_state(), rng)
    resumed = run(tiny("ppo", f"resume={tmp_path / 'checkpoints' / 'last.pt'}", "budget.env_steps=48"), tmp_path / "r")
    assert resumed.env_steps == 48 and resumed.iteration == 3


def test_gaussian_policy_with_a_state_independent_scale(tmp_path):
    """``policy_net.distribution=normal policy_net.scale=parameter`` (CleanRL's continuous policy): one learned scale
    per action dimension whatever the observation, starting at 1; log-probabilities of that diagonal Gaussian, whose
    deterministic action is its mean, unsquashed; the options survive a checkpoint; unknown values are refused."""
    options = ["algo.policy_net.distribution=normal", "algo.policy_net.scale=parameter"]
    trained = run(tiny("ppo", *options), tmp_path)
    actor = load_policy(torch.load(tmp_path / "checkpoints" / "last.pt", weights_only=True),
                        make_env(tiny("ppo"), 5, "cpu"), "cpu")
    obs = TensorDict(observation=3 * torch.randn(5, trained.eval_env.observation_spec["observation"].shape[-1]),
                     batch_size=[5])
    with torch.no_grad():
        sampled = actor(obs.clone())
        assert torch.equal(sampled["scale"], sampled["scale"][:1].expand(5, -1))
        expected = torch.distributions.Normal(sampled["loc"], sampled["scale"]).log_prob(sampled["action"]).sum(-1)
        torch.testing.assert_close(sampled["action_log_prob"], expected)
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            assert torch.equal(actor(obs.clone())["action"], sampled["loc"])
    untrained = make_actor(make_env(tiny("ppo"), 5, "cpu"), tiny("ppo", *options).algo.policy_net, "cpu")
    assert torch.equal(untrained(obs.clone())["scale"], torch.ones(5, 1))
    with pytest.raises(ValueError, match="policy_net.distribution.*beta"):
        run(tiny("ppo", "algo.policy_net.distribution=beta"), tmp_path / "bad")


@pytest.mark.parametrize("algo", ["ppo", "sac"])
def test_hydra_override_smoke(algo, tmp_path):
    finished = run(tiny(algo, "logger=csv"), tmp_path)
    assert finished.iteration == 2 and finished.env_steps == 32
    assert (tmp_path / "curves.png").is_file() and (tmp_path / "checkpoints" / "last.pt").is_file()
    assert any((tmp_path / "logs").rglob("*.csv"))


def test_lr_falls_linearly_to_zero_at_the_env_step_budget(tmp_path):
    """Three updates of 16 env steps: the schedule spans exactly them and leaves the rate at 0."""
    finished = run(tiny("ppo", "algo.anneal_lr=true", "algo.lr=1e-3", "budget.env_steps=48"), tmp_path)
    schedule = finished.state["lr_schedule"]
    assert finished.iteration == 3 and schedule.lr_lambdas[0].total == 3
    assert finished.state["optim"].param_groups[0]["lr"] == schedule.get_last_lr()[0] == 0.0
    with pytest.raises(ValueError, match="budget.env_steps"):
        run(tiny("ppo", "algo.anneal_lr=true", "budget.env_steps=null", "budget.minutes=1"), tmp_path / "no_budget")


def test_bad_config_fails_fast():
    with pytest.raises(Exception, match="nope"):
        config("env=nope")
    with pytest.raises(Exception, match="no_such_key"):
        config("algo.no_such_key=1")


def test_divergence_stops_naming_the_step(tmp_path):
    with pytest.raises(TrainingDiverged, match="at env step 16"):
        run(tiny("ppo", "algo.reward_scale=nan"), tmp_path)


def test_running_norm_matches_the_samples_statistics():
    """With decay 1 the statistics are exactly the mean and (population) variance of every sample added, each once:
    whole batches at steps, only the flagged rows at a partial reset. Float32 running averages over 50 batches
    agree with a float64 reference to ~1e-6 relative; 1e-4 leaves room for the lerp's rounding."""
    torch.manual_seed(0)
    norm = RunningNorm({"observation": (3,)}, eps=1e-4)
    seen = []
    for i in range(50):
        x = torch.randn(64, 3) * torch.tensor([1.0, 5.0, 0.1]) + torch.tensor([2.0, -3.0, 0.5])
        if i % 5 == 4:  # a partial reset: 1 to 9 envs restarted
            rows = torch.zeros(64, dtype=torch.bool)
            rows[torch.randperm(64)[:i // 5 + 1]] = True
            out = norm._reset(TensorDict(_reset=rows[:, None], batch_size=[64]),
                              TensorDict(observation=x.clone(), batch_size=[64]))
            seen.append(x[rows])
        else:
            out = norm._step(TensorDict(batch_size=[64]), TensorDict(observation=x.clone(), batch_size=[64]))
            seen.append(x)
    seen = torch.cat(seen).double()
    assert norm.observation_count.item() == len(seen)
    mean, std = seen.mean(0), seen.std(0, unbiased=False)
    torch.testing.assert_close(out["observation"].double(), (x.double() - mean) / std, rtol=1e-4, atol=1e-4)
    norm.freeze()
    before = norm.state_dict()
    norm._step(TensorDict(batch_size=[64]), TensorDict(observation=x + 100, batch_size=[64]))
    assert all(torch.equal(before[k], v) for k, v in norm.state_dict().items())


def test_running_norm_keeps_constant_features_finite_and_forgets_with_decay():
    """TorchRL's VecNormV2 takes ``E[x^2] - E[x]^2`` of decayed running means as the variance. For a constant
    feature (Humanoid's body masses) that rounds below zero, and its square root is NaN: this stopped Humanoid PPO
    at 87k env steps. ``RunningNorm`` clamps the variance at zero. With decay 0.99 per sample, batches of 64 and a
    jump of the random features' mean from 0 to 10 halfway, the statistics follow the jump: after 100 more batches
    (6400 samples, a weight of 0.99^6400 ~ 1e-28 left on the old ones) the new features normalise to mean 0 and std
    1, to within the sampling noise of the last ~100 samples the decay keeps (~0.1, so 0.3)."""
    constants = torch.linspace(0.3, 9.7, 40)
    torch.manual_seed(0)
    norm = RunningNorm({"observation": (42,)}, decay=0.99, eps=1e-4)
    for i in range(200):
        x = torch.cat((constants.expand(64, -1), torch.randn(64, 2) + (10.0 if i >= 100 else 0.0)), -1)
        out = norm._step(TensorDict(batch_size=[64]), TensorDict(observation=x.clone(), batch_size=[64]))["observation"]
    assert torch.isfinite(out).all()
    # a constant c normalises to (c - mean) / eps: float32 rounding of the mean (~1e-7 c) over eps = 1e-4 is ~1e-3 c
    assert out[:, :40].abs().max() < 1e-2 * constants.max()
    assert out[:, 40:].mean(0).abs().max() < 0.3 and (out[:, 40:].std(0) - 1).abs().max() < 0.3


def test_running_norm_loads_a_vecnorm_checkpoint():
    """Checkpoints written before RunningNorm hold TorchRL VecNormV2's state: they load with the same statistics."""
    torch.manual_seed(0)
    old = VecNormV2(in_keys=["observation"], decay=1.0, eps=1e-4, reduce_batch_dims=True)
    x = torch.randn(64, 5) * 3 + 1
    expected = old._step(TensorDict(observation=x.clone(), batch_size=[64]),
                         TensorDict(observation=x.clone(), batch_size=[64]))["observation"]
    norm = RunningNorm({"observation": (5,)}, eps=1e-4)
    norm.load_state_dict(old.state_dict())
    torch.testing.assert_close(norm.normalize("observation", x), expected)
    assert norm.observation_count.item() == 64

def test_the_console_names_the_tuned_file_or_its_absence():
    from torchsim.algos.train import tuned_settings

    assert tuned_settings(config("algo=ppo", "env=ant")) == (
        "settings: algos/configs/tuned/ppo_ant.yaml over algo/ppo.yaml and env/ant.yaml")
    assert "no tuned file for sac on fetch" in tuned_settings(config("algo=sac", "env=fetch"))
