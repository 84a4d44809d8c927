"""The on-disk kernel cache (``torchsim.execution.kernel.cache``) under faults: a truncated or altered entry is
rebuilt (with one warning) instead of failing or running, an unwritable cache directory falls back to a private
one (with one warning), and a kernel built for another CPU or compiler is never reused.

A hinged pendulum's spring step: its kernel traces and compiles in a few seconds."""

import warnings

import pytest
import torch

import torchsim
from torchsim.execution.kernel import emit_cpp
from torchsim.execution.kernel.step import StepKernel
from models import PENDULUM


def _pendulum():
    sys = torchsim.load_mjcf(PENDULUM, method="spring", dtype=torch.float64)
    state = torchsim.init(sys, torch.tensor([[0.3], [-0.2], [1.0]], dtype=torch.float64),
                          torch.zeros(3, sys.nv, dtype=torch.float64))
    return sys, state, torch.zeros(3, sys.nu, dtype=torch.float64)


def _libraries(root):
    return sorted((root / "cpp").glob("*.so"))


def _expect_reference(kernel, sys, state, ctrl):
    torch.testing.assert_close(kernel(sys, state, ctrl).q, torchsim.step(sys, state, ctrl).q, rtol=0, atol=1e-12)


@pytest.mark.parametrize("damage", ["truncated", "altered", "no digest"])
def test_a_damaged_library_is_rebuilt_with_one_warning(damage, tmp_path, monkeypatch):
    monkeypatch.setenv("TORCHSIM_CACHE_DIR", str(tmp_path))
    sys, state, ctrl = _pendulum()
    StepKernel(sys)
    [library] = _libraries(tmp_path)
    data = library.read_bytes()
    if damage == "no digest":  # an entry of an older torchsim
        library.with_name(library.name + ".sha256").unlink()
    else:  # a new file, not the one this process has mapped (writing into a loaded library kills the process)
        damaged = data[:len(data) // 2] if damage == "truncated" else data[:1000] + bytes([data[1000] ^ 1]) + data[1001:]
        (tmp_path / "damaged").write_bytes(damaged)  # altered: same size, one bit; the digest, not the size, tells
        (tmp_path / "damaged").replace(library)
    with pytest.warns(UserWarning, match="does not match its recorded digest") as caught:
        kernel = StepKernel(sys)
    assert len(caught) == 1
    assert library.read_bytes() == data  # built again, the same code
    _expect_reference(kernel, sys, state, ctrl)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an intact entry loads silently
        StepKernel(sys)


def test_an_unwritable_cache_directory_falls_back_with_one_warning(tmp_path, monkeypatch):
    blocker = tmp_path / "a file"
    blocker.write_text("not a directory")
    monkeypatch.setenv("TORCHSIM_CACHE_DIR", str(blocker / "cache"))  # cannot be created, even by root
    sys, state, ctrl = _pendulum()
    with pytest.warns(UserWarning, match="cannot be written") as caught:
        kernel = StepKernel(sys)
        StepKernel(sys)
    assert len(caught) == 1
    _expect_reference(kernel, sys, state, ctrl)


def test_another_cpu_or_compiler_gets_its_own_library(tmp_path, monkeypatch):
    """``-march=native`` code may not run on another CPU sharing the cache (a cluster's home directory)."""
    monkeypatch.setenv("TORCHSIM_CACHE_DIR", str(tmp_path))
    sys, state, ctrl = _pendulum()
    StepKernel(sys)
    monkeypatch.setattr(emit_cpp, "_cpu_flags", lambda: "another CPU: flags sse2")
    StepKernel(sys)
    monkeypatch.setattr(emit_cpp, "_compiler_version", lambda: "g++ (another build) 99.1")
    _expect_reference(StepKernel(sys), sys, state, ctrl)
    assert len(_libraries(tmp_path)) == 3
