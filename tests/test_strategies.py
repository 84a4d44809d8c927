"""Every strategy a ``torchsim.Stepper`` runs agrees with the reference step (``torchsim.step``) on every model the
envs ship: spring through ``rows`` and ``loop``, xpbd through ``calls``; 20 steps, at batch 1 and at a batch of two
cut into two parts of one env, which two threads step at once (``rows`` steps whole batches: its batch of two runs
the row graph that serves every batch, its batch of one its own).

In float64: a strategy reorders the step's sums, and in float32 that rounding, amplified by the stiff joint springs
and by xpbd's velocities from position changes (``dx / h``, h = 0.5 ms), already moves velocities by ~1e-3 m/s in
one step from the same state (measured on the Ant), which would hide an error of that size. In float64 the same
reordering stays below 1e-10 over the 20 steps, so the 1e-8 bound below leaves room for rounding and none for a
wrong term. ``test_compile.py`` checks the compiled float32 steps.

The steppers run with the ``aot_eager`` backend: each strategy's own graphs (the row graph; dynamo's graph of the
whole step with its ``while_loop``; the separate substep and step end), substep loop and parts, executed op by op.
Inductor's code generation for them takes minutes per model on two cores; it is checked on a small model in
``test_compile.py``, and on every model by the opt-in ``TORCHSIM_TEST_BACKEND=inductor python -m pytest
tests/test_strategies.py`` (about five minutes per model).
"""

import os

import numpy as np
import pytest
import torch

import torchsim
from models import SHIPPED, load_model, random_q

BACKEND = os.environ.get("TORCHSIM_TEST_BACKEND", "aot_eager")
CASES = [("spring", "rows"), ("spring", "loop"), ("xpbd", "calls")]
STEPS = 20


def _start(path, method: str, batch: int):
    """The model in float64; ``batch`` starts with joints anywhere in their range, free bodies at their initial
    height in a random orientation and slides near their initial value (so bodies fall, tumble and land: contacts
    act within the 20 steps), random velocities; a random control per step."""
    xml, m = load_model(path)
    sys = torchsim.load_mjcf(xml, method=method, dtype=torch.float64)
    rng = np.random.default_rng(0)
    q = random_q(m, batch, rng)
    for j in range(m.njnt):
        a = m.jnt_qposadr[j]
        if m.jnt_type[j] == 0:  # free: its initial position, raised a little
            q[:, a:a + 3] = m.qpos0[a:a + 3] + [0.0, 0.0, 0.1]
        elif m.jnt_type[j] == 2:  # slide
            q[:, a] = m.qpos0[a] + rng.uniform(-0.05, 0.05, batch)
    state = torchsim.init(sys, torch.tensor(q, dtype=torch.float64),
                          torch.tensor(rng.normal(0.0, 0.5, (batch, sys.nv)), dtype=torch.float64))
    ctrl = torch.tensor(rng.uniform(-1, 1, (STEPS, batch, sys.nu)), dtype=torch.float64)
    return sys, state, ctrl


@pytest.mark.parametrize("method,strategy", CASES, ids=lambda x: x)
@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.stem)
def test_strategy_agrees_with_reference(path, method, strategy):
    sys, start, ctrl = _start(path, method, batch=2)
    stepper = torchsim.Stepper(sys, strategy, part_size=1, threads=2, backend=BACKEND)
    assert stepper.strategy == strategy
    for batch in (1, 2):
        reference = strategy_state = torchsim.State(*(x[:batch] for x in start))
        if strategy != "rows":
            assert stepper.parts.sizes(strategy_state) == [1] * batch
        worst = 0.0
        with torch.no_grad():  # as collectors step envs
            for t in range(STEPS):
                reference = torchsim.step(sys, reference, ctrl[t, :batch])
                strategy_state = stepper(strategy_state, ctrl[t, :batch])
                worst = max(worst, *((a - b).abs().max().item() for a, b in zip(reference[:6], strategy_state[:6])))
        moved = (reference.x_pos - start.x_pos[:batch]).abs().max().item()
        print(f"{path.stem} {method} {strategy} batch {batch}: max |reference - {strategy}| {worst:.1e} over "
              f"{STEPS} steps; bodies moved up to {moved:.2f} m")
        assert not reference.diverged.any() and torch.equal(reference.diverged, strategy_state.diverged)
        assert moved > 1e-3
        assert worst < 1e-8
