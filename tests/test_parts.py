"""A batch stepped as parts on worker threads (``torchsim.execution.parts``) gives the whole-batch results exactly.

Eager steps here (the parts machinery does not depend on compilation, and compiling would cost minutes); a compiled
``torchsim.Stepper`` (strategies ``loop`` and ``calls``) differs only in which step function each part calls.
"""

import pytest
import torch

import torchsim
from models import ANT, F64
from torchsim import pipeline
from torchsim.execution import parts

PART = 40
BATCH = 3 * PART + 1  # parts of 31, 30, 30, 30: two sizes, shared by two threads


def _step(cut: parts.Parts, sys, state, ctrl):
    """The reference step of ``state``'s batch as ``cut`` steps it."""
    return cut.step(pipeline.run_substeps, sys, state, ctrl, cut.sizes(state))


def _randomised_ant():
    """The ant with per-env masses and friction, and a start with hinges and velocities perturbed per env."""
    sys = torchsim.load_mjcf(str(ANT), dtype=F64)
    gen = torch.Generator().manual_seed(7)
    mass = sys.body_mass * (0.7 + 0.6 * torch.rand(BATCH, 1, generator=gen, dtype=F64))
    groups = tuple(g._replace(friction=g.friction * torch.rand(BATCH, 1, generator=gen, dtype=F64))
                   for g in sys.contact_groups)
    sys = sys.replace(body_mass=mass, contact_groups=groups)
    q = sys.q0.expand(BATCH, -1).clone()
    q[:, 7:] += 0.4 * torch.rand(BATCH, sys.nq - 7, generator=gen, dtype=F64) - 0.2
    qd = 0.3 * torch.randn(BATCH, sys.nv, generator=gen, dtype=F64)
    lo, hi = sys.act_ctrl_range.unbind(-1)
    ctrl = lo + (hi - lo) * torch.rand(3, BATCH, sys.nu, generator=gen, dtype=F64)
    return sys, torchsim.init(sys, q, qd), ctrl


def test_parts_equal_whole_batch():
    sys, start, ctrl = _randomised_ant()
    bad_ctrl = ctrl.clone()
    bad_env = PART + 3  # in the second part
    bad_ctrl[1, bad_env, 0] = float("nan")
    runs = {}
    for name, size, workers in (("whole", 0, 1), ("parts", PART, 2)):
        cut = parts.Parts(size, workers)
        assert cut.sizes(start) == ([BATCH] if size == 0 else [31, 30, 30, 30])
        state, bad = start, start
        for k in range(3):  # the first step in parts runs them one after another (compilation), later ones on threads
            state, bad = _step(cut, sys, state, ctrl[k]), _step(cut, sys, bad, bad_ctrl[k])
        runs[name] = state, bad
    # Eager kernels block their loops by batch size, so an env's arithmetic differs from the whole batch's at the
    # rounding level (measured: 2e-15 in poses, 6e-13 in velocities after 3 steps); an env leaking into another
    # part, or a part given another part's parameters, would differ by O(1).
    for whole, split in zip(runs["whole"], runs["parts"]):
        assert torch.equal(whole.diverged, split.diverged)
        for a, b in zip(whole[:6], split[:6]):
            assert (a - b).abs().max() < 1e-10
    state, bad = runs["parts"]
    assert bad.diverged.nonzero().flatten().tolist() == [bad_env]
    assert not state.diverged.any()
    keep = torch.arange(BATCH) != bad_env
    assert all(torch.equal(a[keep], b[keep]) for a, b in zip(state, bad))  # same parts: bit for bit


def test_part_sizes():
    _, state, _ = _randomised_ant()
    assert parts.Parts(512, 2).sizes(torchsim.State(*(x[:PART] for x in state))) == [PART]  # smaller: whole
    assert parts.Parts(30, 2).sizes(torchsim.State(*(x[:120] for x in state))) == [30] * 4  # a multiple: one size


def test_batched_field_of_another_batch_size_is_rejected():
    sys, state, _ = _randomised_ant()
    with pytest.raises(ValueError, match="leading batch dimension of 100"):
        parts.system_part(sys, 100, 0, 50)


def test_workers_step_in_the_callers_grad_mode():
    """Grad mode is per thread, and the workers step in the caller's: with grad enabled, the envs stepped on the
    worker thread are differentiable in their own per-env masses (and only theirs); under ``no_grad`` the joined
    state records no graph."""
    sys, state, ctrl = _randomised_ant()
    sys = sys.replace(body_mass=sys.body_mass.clone().requires_grad_())
    cut = parts.Parts(PART, 2)
    _step(cut, sys, state, ctrl[0])  # the first step runs its parts on this thread alone
    with torch.no_grad():
        assert not _step(cut, sys, state, ctrl[0]).x_pos.requires_grad
    moved = _step(cut, sys, state, ctrl[0]).x_pos
    (mass_grad,) = torch.autograd.grad(moved[-PART:, 0, 2].sum(), sys.body_mass)  # envs of the worker's parts
    assert mass_grad[-PART:].abs().sum() > 0 and mass_grad[:BATCH - PART].abs().sum() == 0
