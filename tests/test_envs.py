"""The TorchRL environment suite: specs, batching, partial and native resets, rewards, bad input, randomisation."""

import mujoco
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.envs.utils import check_env_specs

import torchsim
import torchsim.envs as envs
from torchsim import actuators
from torchsim.lanes import from_lanes, to_lanes

NAMES = envs.list("physics")


def test_list_and_make():
    assert NAMES == ["ant", "halfcheetah", "humanoid", "reacher", "hopper", "walker2d", "inverted_pendulum",
                     "inverted_double_pendulum", "pusher", "ur5e_reach", "grasp", "fetch"]
    with pytest.raises(ValueError, match="unknown env 'antt'.*ant, halfcheetah"):
        envs.make("antt")
    env = envs.make("hopper", num_envs=3)
    assert isinstance(env, envs.Hopper) and env.batch_size == (3,)


@pytest.mark.parametrize("name", NAMES)
def test_env_api(name):
    """check_env_specs; a 22-step random rollout (three 7-step episodes and the start of a fourth, so per-env partial
    resets happen three times) stays finite; the Collector runs."""
    torch.manual_seed(0)
    env = envs.make(name, num_envs=15, episode_length=7)  # the task's own physics settings
    check_env_specs(env, break_when_any_done="both")
    for spec in (env.observation_spec["observation"], env.action_spec, env.reward_spec, env.full_done_spec["done"]):
        assert spec.shape[0] == 15

    rollout = env.rollout(22, break_when_any_done=False)
    assert rollout.batch_size == (15, 22)
    for key in ("observation", ("next", "observation"), ("next", "reward")):
        assert torch.isfinite(rollout[key]).all(), key
    done = rollout["next", "done"].squeeze(-1)
    assert (done == (rollout["next", "terminated"] | rollout["next", "truncated"]).squeeze(-1)).all()
    # No episode outlives the limit, and every episode after a done starts afresh (step counter restarted).
    steps_since_reset = torch.zeros(15, dtype=torch.long)
    for t in range(22):
        steps_since_reset += 1
        assert (rollout["next", "truncated"][:, t, 0] == (steps_since_reset == 7)).all()
        steps_since_reset = torch.where(done[:, t], 0, steps_since_reset)
    # Fresh noise per episode: first observations of consecutive episodes of env 0 differ.
    starts = torch.cat((torch.tensor([0]), torch.nonzero(done[0, :-1]).flatten() + 1))
    first_obs = rollout["observation"][0, starts]
    assert len(starts) >= 2 and not torch.allclose(first_obs[0], first_obs[1])

    collector = Collector(env, policy=None, frames_per_batch=30, total_frames=60)
    batches = [batch for batch in collector]
    collector.shutdown()
    assert len(batches) == 2 and batches[0].batch_size == (15, 2)


def test_staggered_episodes():
    """``stagger_episodes``: after a full reset each env's first episode is truncated at its own step in
    ``[1, episode_length]``, spread over that range; every later episode has the full length."""
    torch.manual_seed(0)
    env = envs.make("reacher", num_envs=64, episode_length=10, stagger_episodes=True)
    truncated = env.rollout(25, break_when_any_done=False)["next", "truncated"][..., 0]  # (64, 25)
    first = truncated.int().argmax(-1) + 1  # step of the first truncation
    assert first.min() >= 1 and first.max() <= 10 and len(first.unique()) >= 8
    for env_first, row in zip(first.tolist(), truncated):
        assert row.nonzero().flatten().tolist() == [t - 1 for t in range(env_first, 26, 10)]
    plain = envs.make("reacher", num_envs=4, episode_length=10)
    assert plain.rollout(10, break_when_any_done=False)["next", "truncated"][:, -1].all()


def test_partial_resets_draw_each_start_once_and_follow_the_seed():
    """Restarted envs take their start states from a pool drawn a batch at a time (``_pooled_starts``): every
    restart gets a new state, also across the pool's refills; each is a whole start state (the kinematics of its own
    ``q``, within the reset noise of the keyframe); the envs not flagged keep theirs; and a seed replays them."""
    env = envs.make("ant", num_envs=4)
    flagged = torch.tensor([True, False, True, True])

    def restarts(seed):
        env.set_seed(seed)
        env.reset()
        kept = env.state.q[1].clone()
        states = []
        for _ in range(5):  # 15 restarts from a pool of 4: refilled four times
            env.reset(TensorDict(_reset=flagged[:, None], batch_size=[4]))
            states.append(torchsim.State(*(x[flagged].clone() for x in env.state)))
            assert torch.equal(env.state.q[1], kept)
        return torchsim.State(*(torch.cat(xs) for xs in zip(*states)))

    first = restarts(3)
    assert len(torch.unique(first.q, dim=0)) == 15
    assert ((first.q - env.init_q)[:, 7:].abs() <= env.noise_q[1] + 1e-6).all()  # joints: uniform noise
    rebuilt = torchsim.init(env.sys, first.q, first.qd)
    for name, x, y in zip(first._fields, first, rebuilt):
        torch.testing.assert_close(x, y, msg=name)
    for x, y in zip(restarts(3), first):
        assert torch.equal(x, y)


def _random_start(env, n, seed):
    torch.manual_seed(seed)
    return env._sample_init(n)


@pytest.mark.parametrize("name", ["ant", "reacher", "ur5e_reach", "grasp", "fetch"])
def test_batch_independence(name):
    """Env i of a batch of 8 follows the trajectory it follows alone (same start, task and actions; float64)."""
    batch = envs.make(name, num_envs=8, dtype=torch.float64)
    q, qd = _random_start(batch, 8, seed=1)
    task = batch._sample_task(torchsim.init(batch.sys, q, qd))
    actions = 2 * torch.rand(3, 8, batch.sys.nu, dtype=torch.float64) - 1
    obs_batch = _run(batch, q, qd, actions, task)
    i = 5
    alone = envs.make(name, num_envs=1, dtype=torch.float64)
    obs_alone = _run(alone, q[i:i + 1], qd[i:i + 1], actions[:, i:i + 1], task[i:i + 1])
    torch.testing.assert_close(obs_batch[:, i:i + 1], obs_alone, atol=1e-6, rtol=0)


def _run(env, q, qd, actions, task=None):
    env.set_state(q, qd, task)
    out = []
    for a in actions:
        td = env.step(TensorDict(action=a, batch_size=env.batch_size))
        out.append(td["next", "observation"])
    return torch.stack(out)


def _states(env, q_before, q_after, qd=None):
    """States ``before``/``after`` built from generalized coordinates (batch 1, float64)."""
    as_t = lambda x: torch.as_tensor(np.asarray(x), dtype=torch.float64)[None]  # noqa: E731
    qd = torch.zeros(1, env.sys.nv, dtype=torch.float64) if qd is None else as_t(qd)
    return torchsim.init(env.sys, as_t(q_before), qd), torchsim.init(env.sys, as_t(q_after), qd)


def _ctrl(env, action):
    return env._ctrl(torch.as_tensor(np.asarray(action), dtype=torch.float64).expand(1, env.sys.nu))


def test_locomotion_rewards_and_terminations():
    ant = envs.make("ant", dtype=torch.float64)
    q0 = ant.init_q.numpy()
    moved = q0.copy()
    moved[0] += 1.0 * ant.dt  # 1 m/s forward over one env step
    before, after = _states(ant, q0, moved)
    assert ant._reward(before, after, _ctrl(ant, 0.0)).item() == pytest.approx(2.0, abs=1e-9)  # vx + 1
    assert ant._reward(before, after, _ctrl(ant, 1.0)).item() == pytest.approx(2.0 - 0.5 * 8, abs=1e-9)
    for z, ended in ((0.55, False), (0.15, True), (1.05, True)):
        q = q0.copy()
        q[2] = z
        assert bool(ant._terminated(_states(ant, q, q)[0])) == ended, z

    cheetah = envs.make("halfcheetah", dtype=torch.float64)
    q0 = cheetah.init_q.numpy()
    moved = q0.copy()
    moved[0] += 2.0 * cheetah.dt
    before, after = _states(cheetah, q0, moved)
    assert cheetah._reward(before, after, _ctrl(cheetah, 1.0)).item() == pytest.approx(2.0 - 0.1 * 6, abs=1e-9)
    assert not cheetah._terminated(after).item()

    hopper = envs.make("hopper", dtype=torch.float64)
    q0 = hopper.init_q.numpy()
    assert not hopper._terminated(_states(hopper, q0, q0)[0]).item()
    for index, value in ((1, 0.6 - 1.25), (2, 0.3), (2, -0.3)):  # fallen (torso below 0.7 m) or tilted > 0.2 rad
        q = q0.copy()
        q[index] = value
        assert hopper._terminated(_states(hopper, q, q)[0]).item(), (index, value)
    moved = q0.copy()
    moved[0] += hopper.dt
    before, after = _states(hopper, q0, moved)
    assert hopper._reward(before, after, _ctrl(hopper, 0.0)).item() == pytest.approx(2.0, abs=1e-9)

    walker = envs.make("walker2d", dtype=torch.float64)
    q0 = walker.init_q.numpy()
    assert not walker._terminated(_states(walker, q0, q0)[0]).item()
    for index, value in ((1, 0.7 - 1.25), (1, 2.1 - 1.25), (2, 1.1)):  # q[1]: torso height change from 1.25 m
        q = q0.copy()
        q[index] = value
        assert walker._terminated(_states(walker, q, q)[0]).item(), (index, value)

    humanoid = envs.make("humanoid", dtype=torch.float64)
    q0 = humanoid.init_q.numpy()
    moved = q0.copy()
    moved[0] += humanoid.dt  # the whole body moves 1 m/s: its COM does too
    before, after = _states(humanoid, q0, moved)
    assert humanoid._reward(before, after, _ctrl(humanoid, 0.0)).item() == pytest.approx(1.25 + 5.0, abs=1e-9)
    assert not humanoid._terminated(before).item()
    q = q0.copy()
    q[2] = 0.9
    assert humanoid._terminated(_states(humanoid, q, q)[0]).item()


def test_humanoid_observation_matches_mujoco():
    """COM-based inertia, COM velocity and actuator forces equal MuJoCo's cinert, cvel and qfrc_actuator."""
    env = envs.make("humanoid", dtype=torch.float64)
    m, d = env.mj_model, mujoco.MjData(env.mj_model)
    rng = np.random.default_rng(0)
    q = env.init_q.numpy() + rng.uniform(-0.3, 0.3, m.nq)
    q[3:7] /= np.linalg.norm(q[3:7])
    qd, ctrl = rng.normal(size=m.nv), rng.uniform(-0.4, 0.4, m.nu)
    d.qpos[:], d.qvel[:], d.ctrl[:] = q, qd, ctrl
    mujoco.mj_forward(m, d)
    state = torchsim.init(env.sys, torch.tensor(q)[None], torch.tensor(qd)[None])
    obs = env._observation(state, torch.tensor(ctrl)[None])[0].numpy()
    expected = np.concatenate((d.qpos[2:], d.qvel, d.cinert[1:].ravel(), d.cvel[1:].ravel(), d.qfrc_actuator))
    np.testing.assert_allclose(obs, expected, atol=1e-9)


def _mj_positions(env, q, names):
    m, d = env.mj_model, mujoco.MjData(env.mj_model)
    d.qpos[:] = q
    mujoco.mj_kinematics(m, d)
    return [d.xpos[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, n)].copy() for n in names]


def test_arm_and_pendulum_rewards_and_terminations():
    rng = np.random.default_rng(1)
    reacher = envs.make("reacher", dtype=torch.float64)
    q = np.array([0.3, -0.5, 0.1, -0.05])
    tip, target = _mj_positions(reacher, q, ["fingertip", "target"])
    action = rng.uniform(-1, 1, 2)
    state = _states(reacher, q, q)[0]
    expected = -np.linalg.norm(tip - target) - (action ** 2).sum()
    assert reacher._reward(state, state, _ctrl(reacher, action)).item() == pytest.approx(expected, abs=1e-9)
    obs = reacher._observation(state, _ctrl(reacher, action))[0].numpy()
    np.testing.assert_allclose(obs[-3:], tip - target, atol=1e-9)

    pusher = envs.make("pusher", dtype=torch.float64)
    q = pusher.init_q.numpy() + rng.uniform(-0.2, 0.2, pusher.sys.nq)
    tip, obj, goal = _mj_positions(pusher, q, ["tips_arm", "object", "goal"])
    action = rng.uniform(-1, 1, 7)
    ctrl = _ctrl(pusher, action)
    state = _states(pusher, q, q)[0]
    expected = -np.linalg.norm(obj - goal) - 0.1 * (ctrl.numpy() ** 2).sum() - 0.5 * np.linalg.norm(tip - obj)
    assert pusher._reward(state, state, ctrl).item() == pytest.approx(expected, abs=1e-9)
    starts, _ = pusher._sample_init(256)
    assert ((starts[:, -4:-2] - starts[:, -2:]).norm(dim=-1) >= 0.17 - 1e-9).all()

    pendulum = envs.make("inverted_pendulum", dtype=torch.float64)
    for angle, ended in ((0.1, False), (0.25, True), (-0.25, True)):
        state = _states(pendulum, [0.0, angle], [0.0, angle])[0]
        assert pendulum._terminated(state).item() == ended
        assert pendulum._reward(state, state, _ctrl(pendulum, 0.0)).item() == 1.0

    double = envs.make("inverted_double_pendulum", dtype=torch.float64)
    upright = _states(double, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])[0]
    tip_z = double._tip(upright)[0, 2].item()
    assert tip_z > 1.0 and not double._terminated(upright).item()
    assert double._reward(upright, upright, _ctrl(double, 0.0)).item() == pytest.approx(10.0 - (tip_z - 2.0) ** 2)
    fallen = _states(double, [0.0, 1.5, 0.0], [0.0, 1.5, 0.0])[0]
    assert double._terminated(fallen).item()


def test_bad_actions():
    env = envs.make("hopper", num_envs=4)
    env.reset()
    for bad, match in ((torch.zeros(4, 2), r"shape \(4, 3\)"), (torch.zeros(4, 3, dtype=torch.float64), "dtype"),
                       (torch.zeros(3, 3), r"shape \(4, 3\)")):
        with pytest.raises(ValueError, match=match):
            env._step(TensorDict(action=bad))
    # Out-of-range actions are clipped to the action spec's [-1, 1].
    q, qd = env._sample_init(4)
    clipped = _run(env, q, qd, torch.full((2, 4, 3), 1.0))
    beyond = _run(env, q, qd, torch.full((2, 4, 3), 5.0))
    torch.testing.assert_close(clipped, beyond, atol=0, rtol=0)


def test_diverging_env_is_contained():
    """A NaN action in env 2 flags that env (terminated, reward 0, state frozen); the others are unaffected."""
    env = envs.make("hopper", num_envs=4, dtype=torch.float64)
    q, qd = _random_start(env, 4, seed=3)
    actions = 2 * torch.rand(2, 4, 3, dtype=torch.float64) - 1
    clean = _run(env, q, qd, actions)
    poisoned_actions = actions.clone()
    poisoned_actions[:, 2] = float("nan")
    env.set_state(q, qd)
    td = env.step(TensorDict(action=poisoned_actions[0], batch_size=[4]))
    assert td["next", "terminated"][2, 0] and td["next", "done"][2, 0] and env.state.diverged.tolist() == [0, 0, 1, 0]
    assert td["next", "reward"][2, 0] == 0.0 and torch.isfinite(td["next", "observation"]).all()
    torch.testing.assert_close(td["next", "observation"][[0, 1, 3]], clean[0][[0, 1, 3]], atol=0, rtol=0)


def test_domain_randomisation_is_per_env():
    """Per-env mass, friction and actuator gain: env i of the batch matches a single env with env i's values."""
    scales = {"mass_scale": torch.tensor([1.0, 1.5, 0.7]), "friction_scale": torch.tensor([1.0, 0.2, 2.0]),
              "actuator_gain_scale": torch.tensor([1.0, 0.5, 1.3])}
    batch = envs.make("hopper", num_envs=3, dtype=torch.float64)
    batch.set_physics(**{k: v.double() for k, v in scales.items()})
    q, qd = _random_start(batch, 3, seed=4)
    actions = 2 * torch.rand(3, 3, 3, dtype=torch.float64) - 1
    obs = _run(batch, q, qd, actions)
    assert not torch.allclose(obs[:, 0], obs[:, 1])
    alone = envs.make("hopper", num_envs=1, dtype=torch.float64)
    alone.set_physics(**{k: float(v[1]) for k, v in scales.items()})
    torch.testing.assert_close(_run(alone, q[1:2], qd[1:2], actions[:, 1:2]), obs[:, 1:2], atol=1e-9, rtol=0)
    with pytest.raises(ValueError, match="unknown physics parameter"):
        batch.set_physics(gravity_scale=2.0)


def test_actuator_gain_scale_keeps_servo_set_points():
    """Scaling a position servo's strength scales its whole force, kp (target - q): the gain and the bias term
    together. A servo held at its target exerts no force at any scale, and away from it the force scales."""
    env = envs.make("ur5e_reach", num_envs=3, dtype=torch.float64)
    env.set_physics(actuator_gain_scale=torch.tensor([1.0, 0.5, 2.0], dtype=torch.float64))
    sys = env.sys
    q = torch.rand(1, sys.dof_qpos.numel(), dtype=torch.float64).expand(3, -1)
    qd = torch.zeros_like(q)
    passive = -sys.dof_stiffness * (q - sys.dof_springref)
    at_target = sys.act_gear * q.index_select(1, sys.act_dof)
    def dof_forces(ctrl):  # the engine's lanes layout: (D, B), (U, B)
        return from_lanes(actuators.dof_forces(sys, to_lanes(q), to_lanes(qd), to_lanes(ctrl))) - passive

    force = dof_forces(at_target)
    assert force.abs().max() < 1e-9
    force = dof_forces(at_target + 0.01)
    assert force[0].abs().min() > 0
    torch.testing.assert_close(force[1:], force[0] * torch.tensor([[0.5], [2.0]], dtype=torch.float64))


# fetch: targets that respawn (task state); 1 substep keeps its traced step small
@pytest.mark.parametrize("name, substeps", [("inverted_pendulum", 2), ("fetch", 1)])
def test_native_autoreset_is_one_graph_and_resets_done_rows(name, substeps):
    env = envs.make(name, num_envs=4, native_autoreset=True, episode_length=2, substeps=substeps)
    td = env.reset()
    td["action"] = env.action_spec.rand()
    explanation = torch._dynamo.explain(env._step_and_maybe_reset)(td)
    assert explanation.graph_count == 1 and explanation.graph_break_count == 0, explanation.break_reasons
    env.reset()
    td = env.reset()
    for t in range(2):
        td["action"] = torch.zeros(4, env.sys.nu)
        out, td = env.step_and_maybe_reset(td)
    # Every env hit the 2-step limit: the "next" observation is invalid (NaN), the root one is a fresh episode.
    assert out["next", "truncated"].all() and torch.isnan(out["next", "observation"]).all()
    assert torch.isfinite(td["observation"]).all() and not td["done"].any()
    assert (env.step_count == 0).all()
