"""Envs in a batch never interact: batched == one-by-one, and a diverging env is contained."""

import functools

import pytest
import torch

import torchsim
from models import ANT, F64, HUMANOID, METHODS

BATCH = 64


def _ant_inputs(sys, steps):
    """sys.q0 with hinges perturbed by U(-0.1, 0.1) per env, and per-env random controls in the ctrl range."""
    gen = torch.Generator().manual_seed(3)
    q = sys.q0.expand(BATCH, -1).clone()
    q[:, 7:] += 0.2 * torch.rand(BATCH, sys.nq - 7, generator=gen, dtype=F64) - 0.1
    qd = torch.zeros(BATCH, sys.nv, dtype=F64)
    lo, hi = sys.act_ctrl_range.unbind(-1)
    ctrl = lo + (hi - lo) * torch.rand(steps, BATCH, sys.nu, generator=gen, dtype=F64)
    return q, qd, ctrl


@pytest.mark.parametrize("method", METHODS)
def test_batch_independence(method):
    sys = torchsim.load_mjcf(str(ANT), method=method, dtype=F64)
    steps = 20
    q, qd, ctrl = _ant_inputs(sys, steps)
    idx = [0, 17, 63]
    batched = torchsim.init(sys, q, qd)
    alone = [torchsim.init(sys, q[i:i + 1], qd[i:i + 1]) for i in idx]
    fields = ("x_pos", "x_quat", "xd_vel", "xd_ang", "q", "qd")

    def differences():
        return {f: max((getattr(a, f)[0] - getattr(batched, f)[i]).abs().max().item() for a, i in zip(alone, idx))
                for f in fields}

    def max_speed():
        return max(batched.xd_vel.abs().max().item(), batched.xd_ang.abs().max().item(), 1.0)

    for k in range(steps):
        batched = torchsim.step(sys, batched, ctrl[k])
        alone = [torchsim.step(sys, a, ctrl[k, i:i + 1]) for a, i in zip(alone, idx)]
        for a, i in zip(alone, idx):
            assert torch.equal(a.diverged[0], batched.diverged[i])
        if k == 0:
            first, first_speed = differences(), max_speed()
    diff, speed = differences(), max_speed()
    print(f"{method}: |batched - alone| after 1 step {first}; after {steps} steps {diff}; max speed {speed:.1f}; "
          f"diverged in batch: {batched.diverged.sum().item()}/{BATCH}")
    # Per-env arithmetic is the same except for batched-kernel blocking: ~1e-15 after one step (times the speed
    # for velocities); a leak between envs would be O(1) there. Round-off then grows with the dynamics'
    # sensitivity (measured ~x2 per step on the violently actuated ant). After 20 steps the brief's 1e-6 applies
    # to poses and coordinates; velocities (xpbd forms them as displacement / h) get 1e-6 of the largest speed.
    assert max(first.values()) < 1e-12 * first_speed
    assert max(diff[n] for n in ("x_pos", "x_quat", "q")) < 1e-6
    assert max(diff[n] for n in ("xd_vel", "xd_ang", "qd")) < 1e-6 * speed
    # Comparing envs frozen by divergence would make the check vacuous (see the report: the spring ant diverges).
    assert not batched.diverged.any(), f"{batched.diverged.sum().item()} of {BATCH} envs diverged"


@functools.lru_cache(maxsize=None)
def _humanoid_runs(method, steps=5, nan_step=2):
    """Humanoid batch run clean and with (env 3) 1e6 m/s initial velocity and (env 5) NaN ctrl at ``nan_step``."""
    sys = torchsim.load_mjcf(str(HUMANOID), method=method, dtype=F64)
    gen = torch.Generator().manual_seed(5)
    q = sys.q0.expand(BATCH, -1).clone()
    q[:, 7:] += 0.2 * torch.rand(BATCH, sys.nq - 7, generator=gen, dtype=F64) - 0.1
    qd = 0.1 * torch.randn(BATCH, sys.nv, generator=gen, dtype=F64)
    lo, hi = sys.act_ctrl_range.unbind(-1)
    ctrl = lo + (hi - lo) * torch.rand(steps, BATCH, sys.nu, generator=gen, dtype=F64)
    bad_qd = qd.clone()
    bad_qd[3, 0] = 1e6
    bad_ctrl = ctrl.clone()
    bad_ctrl[nan_step, 5, 0] = float("nan")
    clean, bad = [torchsim.init(sys, q, qd)], [torchsim.init(sys, q, bad_qd)]
    for k in range(steps):
        clean.append(torchsim.step(sys, clean[-1], ctrl[k]))
        bad.append(torchsim.step(sys, bad[-1], bad_ctrl[k]))
    return clean, bad, nan_step


@pytest.mark.parametrize("method", METHODS)
def test_nan_ctrl_is_contained(method):
    clean, bad, nan_step = _humanoid_runs(method)
    assert not clean[-1].diverged.any(), "precondition: the clean run must not diverge"
    # states[k] is after k steps; the NaN ctrl is used by the step producing states[nan_step + 1]
    for k in range(1, len(bad)):
        assert bool(bad[k].diverged[5]) == (k > nan_step), f"env 5 diverged flag wrong after {k} steps"
        for t in bad[k][:6]:
            assert torch.isfinite(t).all(), "a diverged env must be frozen at finite values"
    for k in range(nan_step + 1, len(bad)):  # frozen at the last good state
        for a, b in zip(bad[k][:6], clean[nan_step][:6]):
            assert torch.equal(a[5], b[5])
    others = torch.ones(len(bad[-1].diverged), dtype=torch.bool)
    others[[3, 5]] = False
    assert not bad[-1].diverged[others].any()
    for a, b in zip(bad[-1], clean[-1]):
        # envs share no arithmetic, so a NaN elsewhere in the batch must not change a single bit
        assert torch.equal(a[others], b[others])


@pytest.mark.parametrize("method", METHODS)
def test_huge_velocity_is_flagged(method):
    clean, bad, _ = _humanoid_runs(method)
    assert not bad[0].diverged.any()  # init does not judge
    assert bool(bad[1].diverged[3]), "1e6 m/s exceeds max_speed and must be flagged after one step"
    for k in range(1, len(bad)):
        assert bool(bad[k].diverged[3])
        for a, b in zip(bad[k][:6], bad[0][:6]):  # frozen at its (finite) initial state
            assert torch.equal(a[3], b[3])
