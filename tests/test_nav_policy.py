"""PointNav's policy and value networks (algos/nav_policy.py) and the PPO recipe on pointnav: shapes, a valid
categorical policy that reads both depth and goal, the env as the recipe wraps it, evaluation's success and SPL, two
PPO iterations through Hydra, and clear errors for bad configs."""

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from torch.distributions import Categorical
from torchrl.envs import ExplorationType, set_exploration_type
from torchrl.envs.utils import check_env_specs

from test_train import QUIET, config
from torchsim.algos import nav_task, physics_task, tasks
from torchsim.algos.env_factory import make_env, make_eval_env
from torchsim.algos.evaluation import evaluate
from torchsim.algos.evaluate import main as evaluate_main
from torchsim.algos.networks import make_actor, make_value
from torchsim.algos.nav_policy import STOP_LOGIT_INIT, NavNet
from torchsim.algos.train import run
from torchsim.envs.nav import PointNav
from torchsim.envs.nav.pointnav import SPLIT_SEEDS, STOP
from torchsim.envs.nav.video import AGENT, episode_frames

# the feed-forward networks (the recipe's LSTM: tests/test_nav_recurrent.py)
SMALL = ["env=pointnav", "env.num_layouts=4", "algo.num_envs=8", "algo.unroll=4", "algo.minibatches=2",
         "eval.episodes=4", "eval.max_steps=8", "algo.policy_net.lstm=0", *QUIET]


@pytest.fixture(scope="module")
def cfg():
    return config(*SMALL)


@pytest.fixture(scope="module")
def env(cfg):
    return make_env(cfg, 6, "cpu", train=True)


def test_pointnav_specifics_live_in_its_task_module(cfg, env):
    """The recipes ask ``tasks`` which module builds an env and what its evaluation adds: ``nav_task`` for PointNav,
    ``physics_task`` for the MJCF tasks and their pixel versions."""
    assert tasks.for_name("pointnav") is nav_task and tasks.for_env(env) is nav_task
    assert tasks.for_name("ant") is physics_task and tasks.for_name("reacher_pixels") is physics_task
    assert nav_task.EPISODE_END_METRICS == ("success", "spl") and not nav_task.SHARES_STEPPER


def test_env_as_the_recipe_wraps_it(cfg, env):
    check_env_specs(env)
    check_env_specs(make_env(cfg, 3, "cpu"))
    assert env.base_env.layout_seeds[0] == SPLIT_SEEDS["train"]
    held_out = make_eval_env(cfg, env)
    assert held_out.batch_size == (4,) and held_out.base_env.layout_seeds[0] == SPLIT_SEEDS["val"]
    assert env.transform[0].in_keys == ["depth"]         # the running normaliser: depth, per pixel


def test_actor_and_value_shapes_and_a_valid_categorical(cfg, env):
    actor, value = make_actor(env, cfg.algo.policy_net, "cpu"), make_value(env, cfg.algo.value_net, "cpu", False)
    td = env.reset()
    out = actor(td.clone())
    assert out["logits"].shape == (6, 4) and out["action"].shape == (6,) and out["action"].dtype == torch.long
    assert ((out["action"] >= 0) & (out["action"] < 4)).all()
    assert torch.isfinite(out["action_log_prob"]).all()
    dist = actor.get_dist(td.clone())
    assert isinstance(dist, Categorical) and torch.allclose(dist.probs.sum(-1), torch.ones(6))
    torch.testing.assert_close(out["action_log_prob"], dist.log_prob(out["action"]))
    # the untrained policy rarely STOPs (its STOP logit starts STOP_LOGIT_INIT lower)
    assert (dist.probs[:, STOP] < dist.probs[:, 1:].min(-1).values * torch.exp(torch.tensor(1 - STOP_LOGIT_INIT))).all()
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        assert torch.equal(actor(td.clone())["action"], out["logits"].argmax(-1))
    assert value(td.clone())["state_value"].shape == (6, 1)
    td = env.rand_step(td)                               # a PPO batch's shape: (envs, time)
    assert actor(torch.stack([td, td], 1))["action"].shape == (6, 2)


def test_policy_reads_depth_and_goal(cfg, env):
    actor = make_actor(env, cfg.algo.policy_net, "cpu")
    td = env.reset()
    logits = actor.module[0](td.clone())["logits"]
    other_depth = td.clone().set("depth", td["depth"].flip(-1) + 1.0)
    other_goal = td.clone().set("pointgoal", td["pointgoal"] + torch.tensor([2.0, 1.5]))
    for changed in (other_depth, other_goal):
        assert not torch.allclose(actor.module[0](changed)["logits"], logits)


def test_one_hot_actions():
    env = PointNav(3, num_layouts=2, one_hot_actions=True)
    actor = make_actor(env, OmegaConf.create({"hidden": [16], "activation": "relu"}), "cpu")
    action = actor(env.reset())["action"]
    assert action.shape == (3, 4) and torch.equal(action.sum(-1), torch.ones(3, dtype=action.dtype))


def test_evaluation_counts_success_and_spl(cfg):
    """The scripted follower, evaluated through the recipe's ``evaluate``: every episode a success, SPL near 1."""
    env = make_env(cfg, 4, "cpu")

    def follower(td):
        return td.set("action", env.base_env.shortest_path_action())

    result = evaluate(env, follower, 500, seed=3)
    assert result.success.all() and (result.spl > 0.8).all() and (result.spl <= 1).all()
    again = evaluate(env, follower, 500, seed=3)     # a seed fixes the held-out episodes
    assert torch.equal(result.length, again.length)


def test_recorded_episode_video(cfg):
    """``evaluate(record=True)`` on a navigation env keeps env 0's frames (reset + one per step) and the video
    draws them: the agent's dot on the map where its position projects, the depth panel the env's depth image."""
    env = make_env(cfg, 2, "cpu")
    result = evaluate(env, lambda td: td.set("action", env.base_env.shortest_path_action()), 500, record=True,
                      seed=5)
    frames = result.trajectory
    assert len(frames) == int(result.length[0]) + 1 and frames[-1].geodesic <= env.base_env.success_distance
    panel = 256
    images = episode_frames(frames, panel)
    assert len(images) == len(frames) and images[0].shape == (panel + 16, 2 * panel + 4, 3)
    for frame, image in ((frames[0], images[0]), (frames[-1], images[-1])):
        agent = (image[:panel, :panel] == AGENT).all(-1)     # the dot and its heading tick
        rows, cols = agent.nonzero()
        px_per_m = panel / (frame.walls.shape[0] * frame.cell)
        dot = (abs(cols - frame.pos[0] * px_per_m) <= 4.5) & (abs(rows - (panel - frame.pos[1] * px_per_m)) <= 4.5)
        assert dot.sum() >= 40                               # a 9-pixel disc around the projected position
    lut_order = images[0][:panel, panel + 4:].astype(int).sum(-1)   # magma_r: nearer is brighter
    depth = np.kron(frames[0].depth, np.ones((panel // frames[0].depth.shape[0],) * 2))
    assert depth.std() > 0.5 and np.corrcoef(depth.ravel(), lut_order.ravel())[0, 1] < -0.9


def test_two_ppo_iterations_through_hydra(tmp_path):
    finished = run(config(*SMALL, "budget.env_steps=64", "logger=csv"), tmp_path)
    assert finished.iteration == 2 and finished.env_steps == 64
    assert len(finished.history["eval_success"]) == len(finished.history["eval_spl"]) == 2
    assert len(finished.recent_success) == len(finished.recent)   # a success flag for each finished training episode
    assert (tmp_path / "checkpoints" / "last.pt").is_file() and any((tmp_path / "logs").rglob("*spl*"))
    # python -m torchsim.evaluate on the checkpoint: success and SPL on held-out layouts, and the episode's GIF
    result = evaluate_main([f"checkpoint={tmp_path / 'checkpoints' / 'last.pt'}", "episodes=2", "max_steps=6",
                            "video=true", "seed=0"])
    assert result["env"] == "pointnav" and 0 <= result["success_rate"] <= 1 and 0 <= result["spl"] <= 1
    assert (tmp_path / "eval.gif").stat().st_size > 0


def test_bad_configs_fail_clearly(cfg, env):
    bad = OmegaConf.create({**OmegaConf.to_container(cfg.algo.policy_net), "encoder": {"chanels": [8]}})
    with pytest.raises(ValueError, match="chanels"):
        NavNet(env.observation_spec["depth"], bad, 4, lambda *a: None, "cpu")
    with pytest.raises(ValueError, match="discrete actions"):
        make_value(env, cfg.algo.value_net, "cpu", with_action=True)
