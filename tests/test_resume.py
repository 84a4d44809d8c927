"""Resuming a training run (``resume=<checkpoint>``): it goes on as the uninterrupted run would, its learning-rate
schedule follows the resumed run's budget, its minutes count from the resume, the checkpoint loads onto each rank's
own device, and a config that changes what is learned, or a budget already spent, is refused.

Runs of 16 or 64 env steps per iteration on eager physics (``tiny_runs``): about a second each."""

import io

import pytest
import torch
from tiny_runs import tiny_ppo

import torchsim.envs
from torchsim.algos.checkpoints import load_checkpoint
from torchsim.algos.common import Run
from torchsim.algos.distributed import Ranks
from torchsim.algos.ppo import PPO
from torchsim.algos.train import run, stopped_by_ctrl_c


def logged_training(monkeypatch) -> list[dict]:
    """The training metrics (losses, rate, returns) that runs log from now on, one dict per iteration."""
    rows, log = [], Run.log

    def spy(self, metrics):
        if "train/loss_objective" in metrics:
            rows.append({k: v for k, v in metrics.items() if k.startswith("train/")})
        log(self, metrics)

    monkeypatch.setattr(Run, "log", spy)
    return rows


def last(out_dir):
    return out_dir / "checkpoints" / "last.pt"


#: 8 envs x 8 steps per iteration, 12-step episodes: episodes end, and restart, inside iterations and across a resume
SHORT_EPISODES = ["algo.unroll=8", "env.episode_length=12"]


def assert_same_training(straight: Run, resumed: Run, rows: list[dict]) -> None:
    """The runs' last two iterations logged the same losses, rate and returns, and they end with the same networks
    and optimiser, bit for bit (one process on the CPU runs every op the same way on the same numbers); ``rows``:
    the straight run's four iterations, then the resumed one's."""
    assert resumed.iteration == straight.iteration == 4 and resumed.env_steps == straight.env_steps == 256
    assert rows[-2:] == rows[2:4]
    for (name, a), b in zip(straight.state["loss"].state_dict().items(), resumed.state["loss"].state_dict().values()):
        assert torch.equal(a, b), name
    moments = [(straight.state["optim"].state[p], resumed.state["optim"].state[q]) for p, q in
               zip(straight.state["loss"].parameters(), resumed.state["loss"].parameters())]
    assert moments and all(torch.equal(a[k], b[k]) for a, b in moments for k in a)


def test_a_run_resumed_from_its_checkpoint_trains_as_if_uninterrupted(tmp_path, monkeypatch):
    """Four iterations straight, checkpointed after the second and fourth, and the run resumed from the second's
    checkpoint (``previous.pt``: as if stopped after it) train alike. The checkpoint holds everything the training
    reads: networks, Adam's moments, the rate's schedule (annealed here), normaliser, counters and random stream,
    and the running episodes (physics states, step counts, returns, the start states drawn ahead for restarts, the
    collector's carried step)."""
    rows = logged_training(monkeypatch)
    cfg = [*SHORT_EPISODES, "budget.env_steps=256", "checkpoint_every=2"]
    straight = run(tiny_ppo(*cfg), tmp_path / "straight")
    checkpoint = tmp_path / "straight" / "checkpoints" / "previous.pt"
    assert load_checkpoint(checkpoint)["counters"]["iteration"] == 2
    assert_same_training(straight, run(tiny_ppo(*cfg, f"resume={checkpoint}"), tmp_path / "resumed"), rows)


def test_a_finished_run_resumed_with_a_larger_budget_trains_as_one_run_to_it(tmp_path, monkeypatch):
    """Two iterations to a budget of 128 env steps, resumed with 256, train as one run to 256. The rate is constant
    here (annealed, the first run's would follow its own budget). The first run evaluated once more than the straight
    one, where its budget ended: evaluations draw from streams of their own, not the training's, so that changes
    nothing."""
    rows = logged_training(monkeypatch)
    cfg = [*SHORT_EPISODES, "algo.anneal_lr=false"]
    straight = run(tiny_ppo(*cfg, "budget.env_steps=256"), tmp_path / "straight")
    first = run(tiny_ppo(*cfg, "budget.env_steps=128"), tmp_path / "first")
    assert [row[0] for row in first.history["eval"]] == [128] and [row[0] for row in straight.history["eval"]] == [256]
    resumed = run(tiny_ppo(*cfg, "budget.env_steps=256", f"resume={last(tmp_path / 'first')}"), tmp_path / "resumed")
    assert_same_training(straight, resumed, rows[:4] + rows[-2:])


def test_a_resumed_schedule_follows_the_new_budget(tmp_path, monkeypatch):
    """A run whose rate fell to 0 at its 32 env-step budget, resumed with a budget of 64, takes its last two updates
    at the rates the 64-step schedule has there (1/2 and 1/4 of ``lr``, as the uninterrupted 64-step run), not at
    0; Adam's moments come from the checkpoint (its step count goes on)."""
    rows = logged_training(monkeypatch)
    anneal = ["algo.anneal_lr=true", "algo.lr=1e-3"]  # as the tuned config, at a round rate
    straight = run(tiny_ppo(*anneal, "budget.env_steps=64"), tmp_path / "straight")
    run(tiny_ppo(*anneal), tmp_path / "first")
    resumed = run(tiny_ppo(*anneal, "budget.env_steps=64", f"resume={last(tmp_path / 'first')}"),
                  tmp_path / "resumed")
    rates = [row["train/lr"] for row in rows]
    assert rates[:4] == pytest.approx([1e-3, 7.5e-4, 5e-4, 2.5e-4]) and rates[4:6] == pytest.approx([1e-3, 5e-4])
    assert rates[6:] == rates[2:4]
    assert resumed.state["optim"].param_groups[0]["lr"] == 0.0  # at the new budget
    adam_steps = [optim.state[next(iter(optim.state))]["step"] for optim in (straight.state["optim"],
                                                                             resumed.state["optim"])]
    assert adam_steps[0] == adam_steps[1] == 4 * 4 * 2  # updates x epochs x minibatches


def test_a_resumed_run_gets_its_minutes_from_the_resume(tmp_path):
    """A checkpoint of a run that took an hour, resumed with ``budget.minutes=1``: the minute counts from the resume,
    so the run trains to its env-step budget (two iterations, not one); its clock (logs, plots) goes on from the
    hour. Evaluation, checkpoint, progress and video settings may change on resume."""
    run(tiny_ppo(), tmp_path / "first")
    ckpt = load_checkpoint(last(tmp_path / "first"))
    ckpt["counters"]["elapsed"] = 3600.0
    torch.save(ckpt, last(tmp_path / "first"))
    resumed = run(tiny_ppo("budget.env_steps=64", "budget.minutes=1", "eval.episodes=3", "checkpoint_every=5",
                           "print_every=2", "video.steps=7", f"resume={last(tmp_path / 'first')}"), tmp_path / "r")
    assert resumed.iteration == 4 and resumed.env_steps == 64
    assert resumed.wall >= 3600


def test_resuming_a_spent_budget_is_refused(tmp_path):
    """The finished run resumed with the budget it reached would stop after one iteration: refused, naming it."""
    run(tiny_ppo(), tmp_path / "first")
    with pytest.raises(ValueError, match=r"already reached budget.env_steps=32 \(env step 32\)"):
        run(tiny_ppo(f"resume={last(tmp_path / 'first')}"), tmp_path / "r")


@pytest.mark.parametrize("change, named", [("algo.policy_net.hidden=[16]", "algo.policy_net.hidden"),
                                           ("algo.lr=1e-2", "algo.lr"),
                                           ("env=inverted_double_pendulum", "env.name")])
def test_resuming_with_a_config_that_changes_what_is_learned_is_refused(change, named, tmp_path):
    """Networks, hyperparameters and env must be the checkpoint's: the error names the key and both values."""
    run(tiny_ppo(), tmp_path / "first")
    with pytest.raises(ValueError, match=rf"differs from the checkpoint's in {named} \("):
        run(tiny_ppo(change, "budget.env_steps=64", f"resume={last(tmp_path / 'first')}"), tmp_path / "r")


@pytest.mark.parametrize("rank", [0, 1])
def test_each_rank_loads_the_checkpoint_onto_its_own_device(rank, tmp_path, monkeypatch):
    """With ``device=cuda`` rank r of a data-parallel run loads the checkpoint onto ``cuda:r`` (its local rank's GPU,
    not every rank onto one), and rank 0 puts the CPU generator's saved state back as a CPU ByteTensor, the only
    kind ``torch.set_rng_state`` takes. On the CPU: ``torch.load`` records the device it is given and loads onto the
    CPU, and Run gets a PPO's state built on the CPU with the ranks of a 2-rank run (a checkpoint of one: a
    different world size is refused)."""
    run(tiny_ppo(), tmp_path / "first")
    path = last(tmp_path / "first")
    ckpt = load_checkpoint(path)
    resumed_cfg = tiny_ppo("budget.env_steps=64", "device=cuda", f"resume={path}")
    ppo = PPO(tiny_ppo())
    two_ranks = Ranks(rank=rank, world_size=2, local_rank=rank)
    devices, rng_states, load = [], [], torch.load
    monkeypatch.setattr(torch, "load", lambda f, map_location, **kw: devices.append(map_location)
                        or load(f, map_location="cpu", **kw))
    monkeypatch.setattr(torch, "set_rng_state", rng_states.append)
    with pytest.raises(ValueError, match=r"world size \(1 ranks in the checkpoint, 2 now\)"):
        Run(resumed_cfg, tmp_path / "r", ppo.state(), ppo.actor, None, ppo.env, two_ranks)
    torch.save({**ckpt, "world_size": 2}, path)
    Run(resumed_cfg, tmp_path / "r", ppo.state(), ppo.actor, None, ppo.env, two_ranks)
    assert devices == [torch.device("cuda", rank)] * 2
    if rank == 0:
        assert len(rng_states) == 1 and rng_states[0].device.type == "cpu"
        assert rng_states[0].dtype == torch.uint8 and torch.equal(rng_states[0], ckpt["rng"])
    else:  # the other ranks seed streams of their own
        assert rng_states == []


def steps(env, td, actions) -> tuple[list, object]:
    """Step ``env`` from ``td`` under ``actions``, restarting ended episodes: each step's output and the last ``td``."""
    outputs = []
    for action in actions:
        out, td = env.step_and_maybe_reset(td.set("action", action))
        outputs.append(out["next"].clone())
    return outputs, td


@pytest.mark.parametrize("name, options", [
    ("inverted_pendulum", {"episode_length": 4, "stagger_episodes": True}),
    ("inverted_pendulum_pixels", {"episode_length": 4, "stagger_episodes": True, "pixel_size": 8,
                                  "render_compile": False}),
    ("pointnav", {"num_layouts": 2, "image_size": 16, "episode_length": 4})])
def test_an_env_continues_its_episodes_from_its_saved_state(name, options):
    """A second env of the task, given the first's ``episode_state`` through a checkpoint's round trip (and the
    global random stream as it was), steps on as the first does under the same actions, restarts of ended episodes
    included: a physics env's start states drawn ahead (episodes end at staggered steps, so the pool is part used),
    a pixel env's frame stacks, PointNav's own generator."""
    torch.manual_seed(0)
    env = torchsim.envs.make(name, num_envs=8, **options)
    _, td = steps(env, env.reset(), [env.action_spec.rand() for _ in range(6)])
    buffer = io.BytesIO()
    torch.save(env.episode_state(), buffer)
    actions = [env.action_spec.rand() for _ in range(8)]
    carried, rng = td.clone(), torch.get_rng_state()
    expected, _ = steps(env, td, actions)
    twin = torchsim.envs.make(name, num_envs=8, **options)
    buffer.seek(0)
    twin.load_episode_state(torch.load(buffer, weights_only=True))
    torch.set_rng_state(rng)
    outputs, _ = steps(twin, carried, actions)
    assert all((got == want).all() for got, want in zip(outputs, expected))
    assert sum(bool(out["done"].any()) for out in outputs) >= 2  # episodes ended, and restarted, on the way


def test_ctrl_c_stops_a_run_with_the_command_that_continues_it(tmp_path):
    """Ctrl-C (SIGINT) during training exits with status 130 and prints the command that resumes the run: its own
    overrides and ``resume=`` its last checkpoint; the command, run, continues it to its budget."""
    import signal
    import subprocess
    import sys
    import time

    from tiny_runs import TINY_PPO

    overrides = [o for o in TINY_PPO if not o.startswith("budget.")] + ["budget.env_steps=10_000_000",
                                                                          "checkpoint_every=1"]
    run_dir = tmp_path / "run"
    # as a terminal starts it: SIGINT raises KeyboardInterrupt (a process started in the background ignores it)
    launch = ("import runpy, signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
              "sys.argv = sys.argv[1:]; runpy.run_module('torchsim.train', run_name='__main__')")
    proc = subprocess.Popen([sys.executable, "-c", launch, "torchsim.train", *overrides, f"hydra.run.dir={run_dir}"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 300
    while not (run_dir / "checkpoints" / "last.pt").exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr[-3000:]
    command = stderr.strip().splitlines()[-1].split()
    assert command[:3] == ["python", "-m", "torchsim.train"] and f"resume={run_dir}/checkpoints/last.pt" in command
    assert set(overrides) <= set(command) and not any(c.startswith("hydra.") for c in command)
    steps = load_checkpoint(run_dir / "checkpoints" / "last.pt")["counters"]["env_steps"]
    resumed = [*command[3:], f"budget.env_steps={steps + 32}", f"hydra.run.dir={tmp_path / 'resumed'}"]
    done = subprocess.run([sys.executable, "-m", "torchsim.train", *resumed], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert load_checkpoint(tmp_path / "resumed" / "checkpoints" / "last.pt")["counters"]["env_steps"] == steps + 32


def test_a_failure_while_ctrl_c_unwinds_is_still_a_stop():
    """A library's clean-up that raises while Ctrl-C's KeyboardInterrupt unwinds through it (seen: a tensordict
    context manager's ``__exit__``) is a stop, exit 130; an error with no interrupt behind it stays an error."""
    def cleanup_fails_during(interrupt: BaseException):
        try:
            raise interrupt
        except BaseException:
            raise RuntimeError("Converting a tensordict to boolean value is not permitted")

    with pytest.raises(RuntimeError) as during_ctrl_c:
        cleanup_fails_during(KeyboardInterrupt())
    with pytest.raises(RuntimeError) as during_an_error:
        cleanup_fails_during(ValueError("a bug"))
    assert stopped_by_ctrl_c(KeyboardInterrupt()) and stopped_by_ctrl_c(during_ctrl_c.value)
    assert not stopped_by_ctrl_c(during_an_error.value) and not stopped_by_ctrl_c(SystemExit(1))
