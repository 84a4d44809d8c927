"""Data-parallel PPO across processes (``torchsim.algos.distributed``), two CPU ranks with gloo.

1. Two ranks, each with half the envs, train for a few iterations: their parameters stay identical (bit for bit:
   the same averaged gradient, the same Adam step), and one update of the two ranks equals one update of a single
   process on the two ranks' data joined (float32 tolerance: the all-reduce sums the halves' gradients in another
   order). Entropy is off (TorchRL estimates a TanhNormal's entropy from random samples, which no two runs share),
   and one minibatch per epoch makes the joined minibatch the single process's.
2. ``torchrun`` with one rank killed mid-run: the run stops within seconds, naming the rank, and the last
   checkpoint is intact.
3. Rank 0 working alone (an evaluation) for longer than the collectives' timeout does not stop the other ranks.
"""

import os
import re
import shutil
import signal
import socket
import subprocess
import datetime
import time

import pytest
import torch
import torch.multiprocessing as mp
from hydra import compose, initialize_config_dir

from torchsim.algos.train import CONFIG_DIR

NUM_ENVS, UNROLL, ITERATIONS = 8, 8, 3
OVERRIDES = ["env=inverted_pendulum", "compile=false", "threads=1", f"algo.num_envs={NUM_ENVS}",
             f"algo.unroll={UNROLL}", "algo.epochs=2", "algo.minibatches=1", "algo.entropy_coeff=0",
             "env.episode_length=50", "logger=", "video.enabled=false"]


def _cfg(extra=()):
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return compose(config_name="config", overrides=[*OVERRIDES, *extra])


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _flat(module) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1) for p in module.parameters()])


def _rank(rank: int, world: int, port: int, results) -> None:
    """One rank: a few training iterations, then one more update, which rank 0 repeats as a single process on the
    joined data. Puts (name, value) pairs on ``results``."""
    os.environ.update(WORLD_SIZE=str(world), RANK=str(rank), LOCAL_RANK=str(rank), LOCAL_WORLD_SIZE=str(world),
                      MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    import torch.distributed as dist

    from torchsim.algos.distributed import Ranks
    from torchsim.algos.ppo import PPO
    from torchsim.algos.train import prepare

    try:
        cfg = _cfg()
        ranks = Ranks.from_env(cfg.device)
        prepare(cfg, ranks)
        ppo = PPO(cfg, ranks)
        no_check = lambda *args: None  # noqa: E731
        batches = iter(ppo.collector)
        for _ in range(ITERATIONS):
            ppo.update(next(batches), no_check)
            ranks.average_moments_(ppo.env.transform[0])
        params = _flat(ppo.loss_module)
        gathered = [torch.empty_like(params) for _ in range(world)]
        dist.all_gather(gathered, params)
        if rank == 0:
            results.put(("max_param_difference_between_ranks", float((gathered[0] - gathered[1]).abs().max())))
        # one more update, which rank 0 repeats as one process on every rank's data joined, from the same start
        keys = ["observation", "action", ppo.loss_module.tensor_keys.sample_log_prob, "done", "terminated",
                *[("next", k) for k in ("observation", "scaled_reward", "done", "terminated")]]
        data = next(batches).select(*keys)
        parts = [torch.zeros_like(data) for _ in range(world)]
        for leaves, leaf in zip(zip(*[part.values(True, True) for part in parts]), data.values(True, True)):
            dist.all_gather(list(leaves), leaf.contiguous())
        start = ({k: v.clone() for k, v in ppo.loss_module.state_dict().items()}, _optim_state(ppo.optim))
        before = _flat(ppo.loss_module)
        ppo.update(data, no_check)
        if rank == 0:
            single = PPO(_cfg(), Ranks())
            single.loss_module.load_state_dict(start[0])
            single.optim.load_state_dict(start[1])
            single.update(torch.cat(parts, 0), no_check)
            after = _flat(ppo.loss_module)
            results.put(("update_size", float((after - before).abs().max())))
            results.put(("max_difference_to_single_process", float((_flat(single.loss_module) - after).abs().max())))
        ranks.close()
    except Exception as err:  # the parent reports it; a silent rank would look like a hang
        results.put(("error", f"rank {rank}: {type(err).__name__}: {err}"))
        raise


def _optim_state(optim) -> dict:
    state = optim.state_dict()
    return {"state": {k: {n: t.clone() if torch.is_tensor(t) else t for n, t in v.items()}
                      for k, v in state["state"].items()}, "param_groups": state["param_groups"]}


def test_two_ranks_stay_identical_and_match_one_process_on_the_joined_batch():
    ctx = mp.get_context("spawn")
    results = ctx.Queue()
    port = _free_port()
    procs = [ctx.Process(target=_rank, args=(r, 2, port, results)) for r in range(2)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(timeout=180)
    values = {}
    while not results.empty():
        key, value = results.get()
        values[key] = value
    for p in procs:
        if p.is_alive():
            p.kill()
    assert "error" not in values, values["error"]
    assert all(p.exitcode == 0 for p in procs), [p.exitcode for p in procs]
    assert values["max_param_difference_between_ranks"] == 0.0
    # float32 sums in another order: ~1e-7 relative on weights of size ~1; the update itself is ~1e-3 (Adam's lr)
    assert values["update_size"] > 1e-5
    assert values["max_difference_to_single_process"] < 1e-5


@pytest.mark.skipif(shutil.which("torchrun") is None, reason="torchrun is not on PATH")
def test_a_dead_rank_stops_the_run_and_leaves_the_checkpoint(tmp_path):
    out = tmp_path / "run"
    cmd = ["torchrun", "--nproc_per_node=2", f"--master_port={_free_port()}", "-m", "torchsim.train", *OVERRIDES,
           "checkpoint_every=1", "budget.minutes=3", "eval.interval_steps=100000000", "eval.at_start=false",
           f"hydra.run.dir={out}"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, "OMP_NUM_THREADS": "1"}, start_new_session=True)
    ckpt = out / "checkpoints" / "last.pt"
    try:
        deadline = time.time() + 120
        while not ckpt.exists() and time.time() < deadline and proc.poll() is None:
            time.sleep(0.5)
        assert ckpt.exists(), "no checkpoint within 120 s"
        rank1 = _child_with_rank(proc.pid, 1)
        os.kill(rank1, signal.SIGKILL)
        killed_at = time.time()
        output, _ = proc.communicate(timeout=60)
        stopped_after = time.time() - killed_at
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode != 0
    assert stopped_after < 30, f"the run took {stopped_after:.0f} s to stop"
    # torchrun's report names the root cause: the rank that died, and how
    assert re.search(r"Root Cause.*rank\s*: 1 \(local_rank: 1\)\s*exitcode\s*: -9", output, re.S), output[-2000:]
    saved = torch.load(ckpt, weights_only=True)
    assert saved["counters"]["iteration"] >= 1 and set(saved["state"]) >= {"loss", "optim", "obs_norm"}


def _slow_rank_zero(rank: int, port: int, results) -> None:
    """Two ranks whose collectives time out after 2 s: rank 0 works alone for 4 s, then both agree, then both
    all-reduce."""
    os.environ.update(WORLD_SIZE="2", RANK=str(rank), LOCAL_RANK=str(rank), LOCAL_WORLD_SIZE="2",
                      MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    import torch.distributed as dist

    from torchsim.algos.distributed import Ranks

    try:
        ranks = Ranks.from_env("cpu", timeout=datetime.timedelta(seconds=2))
        if rank == 0:
            time.sleep(4)  # an evaluation, twice the collectives' timeout
        finished = ranks.agree(rank == 0)
        total = torch.ones(1)
        dist.all_reduce(total)
        results.put((rank, finished, float(total)))
        ranks.close()
    except Exception as err:
        results.put((rank, f"{type(err).__name__}: {err}", None))


def test_rank_zero_working_alone_past_the_collective_timeout_does_not_stop_the_others():
    ctx = mp.get_context("spawn")
    results, port = ctx.Queue(), _free_port()
    procs = [ctx.Process(target=_slow_rank_zero, args=(r, port, results)) for r in range(2)]
    for p in procs:
        p.start()
    outcome = sorted(results.get(timeout=120) for _ in procs)
    for p in procs:
        p.join(timeout=30)
    assert outcome == [(0, True, 2.0), (1, True, 2.0)], outcome


def _child_with_rank(parent: int, rank: int) -> int:
    """The pid of ``parent``'s child process whose environment has ``RANK=rank``."""
    children = open(f"/proc/{parent}/task/{parent}/children").read().split()
    for pid in map(int, children):
        environ = open(f"/proc/{pid}/environ", "rb").read().split(b"\0")
        if f"RANK={rank}".encode() in environ:
            return pid
    raise AssertionError(f"no child of {parent} has RANK={rank}: {children}")
