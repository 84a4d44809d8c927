"""A batch stepped as parts on worker threads (``torchsim.parts``) gives the whole-batch results exactly.

Eager steps here (the parts machinery does not depend on compilation, and compiling would cost minutes); the
compiled path differs only in which substep function each part calls.
"""

import pytest
import torch

import torchsim
from models import ANT, F64
from torchsim import parts

BATCH = 2 * parts.MIN_PART + 1  # two parts of unequal size


@pytest.fixture
def two_workers():
    parts.WORKERS.set(2)
    yield
    parts.WORKERS.set(1)


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


def test_parts_equal_whole_batch(two_workers):
    sys, start, ctrl = _randomised_ant()
    bad_ctrl = ctrl.clone()
    bad_ctrl[1, parts.MIN_PART + 3, 0] = float("nan")  # an env of the second part
    runs = {}
    for name, count in (("whole", 1), ("parts", 2)):
        parts.WORKERS.set(count)
        assert parts.num_parts(start) == count
        state, bad = start, start
        for k in range(3):  # the first step in parts runs them one after another (compilation), later ones on threads
            state, bad = torchsim.step(sys, state, ctrl[k]), torchsim.step(sys, bad, bad_ctrl[k])
        runs[name] = state, bad
    for whole, split in zip(runs["whole"], runs["parts"]):
        for a, b in zip(whole, split):
            assert torch.equal(a, b)  # per-env arithmetic does not depend on the batch it runs in
    state, bad = runs["parts"]
    assert bad.diverged.nonzero().flatten().tolist() == [parts.MIN_PART + 3]
    assert not state.diverged.any()
    keep = torch.arange(BATCH) != parts.MIN_PART + 3
    assert all(torch.equal(a[keep], b[keep]) for a, b in zip(state, bad))


def test_small_batches_stay_whole(two_workers):
    sys, state, _ = _randomised_ant()
    assert parts.num_parts(torchsim.State(*(x[:2 * parts.MIN_PART - 1] for x in state))) == 1


def test_batched_field_of_another_batch_size_is_rejected():
    sys, state, _ = _randomised_ant()
    with pytest.raises(ValueError, match="leading batch dimension of 100"):
        parts.system_part(sys, 100, 0, 50)
