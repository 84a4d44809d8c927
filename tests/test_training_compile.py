"""The compiled engine as training uses it: evaluation reuses the training batch's compiled step, a second
process loads the compiled step (the C++ step kernel, and a row graph with inductor's code) from the on-disk cache, the compiled env step equals the eager one with
per-env physics parameters, and ``torch.compile(torchsim.step)`` warns that it is not the fast path.

Compiling costs tens of seconds even for the small models used here, so each test compiles one thing once.
"""

import json
import logging
import os
import subprocess
import sys
import textwrap

import pytest
import torch
from tensordict import TensorDict

import torchsim
import torchsim.envs
from test_train import QUIET, config
from torchsim.algos.train import run
from torchsim.execution.kernel import step as kernel_step


def test_evaluation_reuses_the_training_graph(tmp_path, caplog, monkeypatch):
    """PPO with ``compile=true``: the training env builds the step (one C++ step kernel, for any batch size) once;
    the evaluation env, with another batch size and the training env's System, builds nothing more, though it is
    evaluated at the first and the last iteration; dynamo compiles nothing of the physics, and the loss it compiles
    is announced by its class. The step cache is empty, on disk and in the process (an earlier test or run may have
    stored this kernel, or traced its program in this worker, which would then load instead of build)."""
    monkeypatch.setenv("TORCHSIM_CACHE_DIR", str(tmp_path / "step_cache"))
    monkeypatch.setattr(kernel_step, "_PROGRAMS", {})
    cfg = config("algo=ppo", "env=inverted_pendulum", "algo.num_envs=8", "algo.unroll=2", "algo.minibatches=2",
                 "budget.env_steps=32", "eval.max_steps=5", "eval.episodes=3", "eval.at_start=true", *QUIET,
                 "compile=true")
    with caplog.at_level(logging.INFO, logger="torchsim"):
        trained = run(cfg, tmp_path)
    assert len(trained.history["eval"]) == 2
    assert (trained.eval_env.batch_size, trained.train_env.batch_size) == ((3,), (8,))
    assert trained.eval_env.base_env.stepper is trained.train_env.base_env.stepper
    assert trained.train_env.base_env.stepper.strategy == "kernel"
    built = [r.getMessage() for r in caplog.records if r.getMessage().startswith(("compiling ", "loaded "))]
    assert len([m for m in built if "spring step" in m and "tracing its row graphs" in m]) == 1, built
    assert len([m for m in built if "spring step" in m and "as C++" in m]) == 1, built
    assert not [m for m in built if "_step_terms" in m or "finish" in m], built
    # the console names what torch.compile compiles: TorchRL's loss forward is a closure that says little alone
    assert [m for m in built if "ClipPPOLoss.forward (torch.compile" in m], built


CACHE_PROBE = textwrap.dedent("""
    import json, logging, sys, torch, torchsim, torchsim.envs
    from torch._dynamo.utils import counters
    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stderr)
    sys_ = torchsim.load_mjcf(str(torchsim.envs.asset_path("inverted_pendulum.xml")))
    stepper = torchsim.Stepper(sys_, sys.argv[1])
    state = torchsim.init(sys_, sys_.q0.expand(8, -1).clone(), torch.zeros(8, sys_.nv))
    state = stepper(state, torch.zeros(8, sys_.nu))
    print(json.dumps({"q": state.q.tolist(), "inductor": dict(counters["inductor"])}))
""")


def test_second_process_loads_the_compiled_step_from_disk(tmp_path):
    """Two processes build the same step with empty caches in ``tmp_path``; the second loads the C++ library the
    first stored (``TORCHSIM_CACHE_DIR``), found without tracing the step, compiles nothing, and gives the same
    result."""
    env = {**os.environ, "TORCHSIM_CACHE_DIR": str(tmp_path / "torchsim"),
           "TORCHINDUCTOR_CACHE_DIR": str(tmp_path / "inductor")}
    runs = [subprocess.run([sys.executable, "-c", CACHE_PROBE, "kernel"], env=env, capture_output=True, text=True,
                           timeout=600) for _ in range(2)]
    for proc in runs:
        assert proc.returncode == 0, proc.stderr[-3000:]
    first, second = (json.loads(proc.stdout.strip().splitlines()[-1]) for proc in runs)
    assert first["q"] == second["q"]
    assert "compiling" in runs[0].stderr and "compiling" not in runs[1].stderr, runs[1].stderr[-3000:]
    assert "loaded the spring step" in runs[1].stderr
    assert list((tmp_path / "torchsim" / "cpp").glob("*.so"))
    assert not second["inductor"]


def test_compiled_env_step_matches_eager_with_per_env_parameters():
    """Domain randomisation (``set_physics`` with a different mass, friction and actuator gain per env) under the
    compiled step: 10 env steps equal the eager ones to float32 tolerance (1e-4: rounding of reordered float32
    arithmetic grown over 10 x 2 physics steps; one step agrees to ~1e-6)."""
    torch.manual_seed(0)
    scales = dict(mass_scale=torch.linspace(0.5, 1.5, 6), friction_scale=torch.linspace(0.5, 2.0, 6),
                  actuator_gain_scale=torch.linspace(0.7, 1.3, 6))
    eager = torchsim.envs.make("inverted_pendulum", num_envs=6)
    eager.set_physics(**scales)
    eager.reset()
    start = (eager.state, eager.task, eager.step_count.clone())
    actions = torch.rand(10, 6, eager.sys.nu) * 2 - 1
    trajectories = []
    for env in (eager, torchsim.envs.make("inverted_pendulum", num_envs=6, stepper="auto")):
        env.set_physics(**scales)
        env.state, env.task, env.step_count = start[0], start[1], start[2].clone()
        obs = []
        for action in actions:
            obs.append(env.step(TensorDict(action=action, batch_size=[6]))["next", "observation"])
        trajectories.append(torch.stack(obs))
    assert env.stepper.strategy == "kernel"  # per-env parameters: inputs of the C++ step
    eager, compiled = trajectories
    assert not torch.equal(eager[:, 0], eager[:, -1])  # the envs differ
    torch.testing.assert_close(compiled, eager, rtol=0, atol=1e-4)


def test_torch_compile_of_step_warns_it_is_not_the_fast_path():
    """Dynamo tracing the reference step warns once, naming the Stepper (traced with the eager backend: what the
    warning is about is the graph dynamo sees, not inductor's code for it; 2 substeps, which dynamo unrolls)."""
    sys_ = torchsim.load_mjcf(str(torchsim.envs.asset_path("inverted_pendulum.xml")), substeps=2)
    state = torchsim.init(sys_, sys_.q0.expand(2, -1).clone(), torch.zeros(2, sys_.nv))
    with pytest.warns(UserWarning, match="torchsim.Stepper"):
        torch.compile(torchsim.step, fullgraph=True, backend="eager")(sys_, state, torch.zeros(2, sys_.nu))
