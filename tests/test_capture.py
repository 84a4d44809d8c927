"""The captured collector step (``capture=true``) on the CPU: the code path a GPU runs as CUDA graphs, without
them. The training env's step is compiled around the kernel operator (``torchsim.execution.step_op``) and the
policy is compiled; a run trains as the uncaptured one does, the same losses iteration by iteration up to the
rounding of inductor's fused float32 ops."""

import math

import pytest
from test_resume import logged_training
from tiny_runs import tiny_ppo

from torchsim.algos.train import run

#: 8 envs x 8 steps per iteration, 12-step episodes (episodes end and restart inside iterations), the kernel stepper
CAPTURED = ["compile=true", "algo.unroll=8", "env.episode_length=12", "budget.env_steps=192"]


def test_a_captured_run_trains_as_the_uncaptured_one(tmp_path, monkeypatch):
    rows = logged_training(monkeypatch)
    plain = run(tiny_ppo(*CAPTURED), tmp_path / "plain")
    captured = run(tiny_ppo(*CAPTURED, "capture=true"), tmp_path / "captured")
    assert captured.train_env.base_env._advance.__name__ == "advance"  # compile_step's
    assert plain.train_env.base_env._advance.__func__ is type(plain.train_env.base_env)._advance
    assert captured.train_env.base_env.stepper.strategy == "kernel"
    assert len(rows) == 6 and captured.env_steps == plain.env_steps == 192
    # float32 rounding of reordered ops (~1e-7 relative), carried through 3 iterations of sampling and Adam steps
    for iteration, (a, b) in enumerate(zip(rows[:3], rows[3:])):
        for key in a:
            assert math.isclose(a[key], b[key], rel_tol=1e-4, abs_tol=1e-6), (iteration, key, a[key], b[key])


def test_capture_needs_the_compiled_step(tmp_path):
    with pytest.raises(ValueError, match="capture=true .* needs compile=true"):
        run(tiny_ppo("capture=true"), tmp_path / "r")
