"""On a machine another process is using, idle OpenMP threads must give their core back quickly: torchsim sets
libgomp's spin count to 1000 (from its default 300,000) where it is imported before torch, as ``python -m
torchsim.train`` does (``benchmarks/bench_contention.py`` measures why; ``docs/reliability.md``). libgomp reports the
value it runs with when ``OMP_DISPLAY_ENV=VERBOSE``."""

import os
import re
import subprocess
import sys

import pytest


def _libgomp_spin_count(code: str, **env) -> str:
    environ = {k: v for k, v in os.environ.items() if k != "GOMP_SPINCOUNT"} | {"OMP_DISPLAY_ENV": "VERBOSE", **env}
    done = subprocess.run([sys.executable, "-c", code], env=environ, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    found = re.search(r"GOMP_SPINCOUNT = '(\d+)'", done.stderr)
    assert found, done.stderr[-2000:]
    return found.group(1)


def test_the_training_entry_point_runs_openmp_with_short_spins():
    assert _libgomp_spin_count("import torchsim.train") == "1000"


@pytest.mark.parametrize("code, env, expected", [
    ("import torchsim", {"GOMP_SPINCOUNT": "50"}, "50"),  # the user's setting wins
    ("import torch, torchsim", {}, "300000"),  # too late: libgomp read its environment when torch loaded it
])
def test_only_an_unset_spin_count_before_torch_is_changed(code, env, expected):
    assert _libgomp_spin_count(code, **env) == expected
