"""Every strategy a ``torchsim.Stepper`` runs agrees with the reference step (``torchsim.step``) on every model the
envs ship: spring through ``rows`` and ``loop``, xpbd through ``calls``; 20 steps, at batch 1 and at a batch of two
cut into two parts of one env, which two threads step at once (``rows`` steps whole batches: its batch of two runs
the row graph that serves every batch, its batch of one its own).

In float64, against the reference's own rounding: a strategy evaluates the step with other formulas for a few
primitives (the per-component forms that ``torch.compile`` and row graphs trace, ``torchsim.spatial``) and the row
graph also reorders sums and folds constants. Where large spring forces nearly cancel, float64 rounding is amplified:
in one Pusher start, cross products of terms of size ~1e12 differ by 2^-11 between the two formulas, which moves the
next state by 1e-3. So each case first measures the reference's own spread (``torchsim.step`` with its eager
formulas against ``torchsim.step`` with the per-component ones, same starts and controls) and bounds the strategy's
difference from the reference by 10x that spread, and at least 1e-8 (the spread is 1e-18 to 2e-10 in the calm
starts; float32 rounding alone moves velocities by ~1e-3 m/s in a step of the stiff springs, so float32 would hide
errors of that size).

The steppers run with the ``eager`` backend (``Stepper(..., backend=...)``): each strategy's own graphs (the row
graph; dynamo's graph of the whole step with its ``while_loop``; the separate substep and step end), substep loop
and parts, executed op by op. Inductor's code generation for them takes minutes per model on two cores; it is
checked in float32 on a small model in ``test_compile.py``. Run op by op, a model still costs 30-140 s of CPU
(a row graph is ~7,600 row ops a substep), so CI runs five models that between them hold every joint kind, contact
shape and loader (the Ant: free root and hinges, capsule and sphere contacts; the Humanoid: 2- and 3-hinge joints;
the Hopper: slides; Fetch: boxes; the UR5e: a URDF arm without contacts), ``rows`` on the Ant and the Humanoid
only. ``TORCHSIM_TEST_ALL_MODELS=1`` runs every shipped model and strategy, and ``TORCHSIM_TEST_BACKEND=inductor``
the generated code (about five minutes of compiling per model).
"""

import os

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from torchsim import spatial
from models import SHIPPED, load_model, random_q

BACKEND = os.environ.get("TORCHSIM_TEST_BACKEND", "eager")
ALL_MODELS = bool(os.environ.get("TORCHSIM_TEST_ALL_MODELS"))
CI_MODELS = ("ant", "humanoid", "hopper", "fetch", "ur5e")
# ``rows`` runs the substep row graph that ``kernel`` turns into C++ (checked on all five), with the step's terms and
# end as dynamo graphs; op by op it costs 30-80 s a model, so CI runs it on the two with the most joint kinds.
ROWS_CI_MODELS = ("ant", "humanoid")
CASES = [("spring", "kernel"), ("spring", "rows"), ("spring", "loop"), ("xpbd", "calls")]
PARAMS = [pytest.param(path, method, strategy, id=f"{path.stem}-{method}-{strategy}")
          for path in SHIPPED if ALL_MODELS or path.stem in CI_MODELS
          for method, strategy in CASES if ALL_MODELS or strategy != "rows" or path.stem in ROWS_CI_MODELS]
STEPS = 20


def _start(path, method: str, batch: int):
    """The model in float64; ``batch`` starts with hinges within 0.1 rad of their initial angle and slides up to 5 cm
    above their initial value (in their range), ball joints and free bodies in a random orientation, free bodies
    0.1 m above their initial position (so bodies fall, tumble and land: contacts act within the 20 steps), random
    velocities; random controls within 30% of the control range's half-width.

    Grasp's claw starts around its ball here (the env starts it 6 m above): the ball is flung, and Grasp's spring
    model (the env ships xpbd: ``envs/targets.py``) diverges within 20 steps. The engine then freezes the env at its
    last good state, so a strategy must flag the same envs and agree on the steps before."""
    xml, m = load_model(path)
    sys = torchsim.load_mjcf(xml, method=method, dtype=torch.float64)
    rng = np.random.default_rng(0)
    q = random_q(m, batch, rng)  # orientations
    free, hinge, slide = (int(k) for k in (mujoco.mjtJoint.mjJNT_FREE, mujoco.mjtJoint.mjJNT_HINGE,
                                           mujoco.mjtJoint.mjJNT_SLIDE))
    for j, kind in enumerate(m.jnt_type.tolist()):
        a = m.jnt_qposadr[j]
        if kind == free:
            q[:, a:a + 3] = m.qpos0[a:a + 3] + [0.0, 0.0, 0.1]
        elif kind in (hinge, slide):
            q[:, a] = m.qpos0[a] + (rng.uniform(-0.1, 0.1, batch) if kind == hinge else rng.uniform(0.0, 0.05, batch))
            if m.jnt_limited[j]:
                q[:, a] = q[:, a].clip(*m.jnt_range[j])
    state = torchsim.init(sys, torch.tensor(q, dtype=torch.float64),
                          torch.tensor(rng.normal(0.0, 0.2, (batch, sys.nv)), dtype=torch.float64))
    mid, half = m.actuator_ctrlrange.mean(1), np.diff(m.actuator_ctrlrange, axis=1)[:, 0] / 2
    ctrl = torch.tensor(mid + 0.3 * half * rng.uniform(-1, 1, (STEPS, batch, sys.nu)), dtype=torch.float64)
    return sys, state, ctrl


def _trajectory(step, state, ctrl, batch: int) -> list:
    states = [torchsim.State(*(x[:batch] for x in state))]
    with torch.no_grad():  # as collectors step envs
        for t in range(STEPS):
            states.append(step(states[-1], ctrl[t, :batch]))
    return states


def _worst(states_a: list, states_b: list) -> float:
    return max((a - b).abs().max().item() for sa, sb in zip(states_a, states_b) for a, b in zip(sa[:6], sb[:6]))


@pytest.mark.parametrize("path,method,strategy", PARAMS)
def test_strategy_agrees_with_reference(path, method, strategy):
    sys, start, ctrl = _start(path, method, batch=2)
    stepper = torchsim.Stepper(sys, strategy, part_size=1, threads=2, backend=BACKEND)
    assert stepper.strategy == strategy

    def reference(state, ctrl):
        return torchsim.step(sys, state, ctrl)

    def reference_per_component(state, ctrl):
        with spatial.component_formulas():
            return torchsim.step(sys, state, ctrl)

    for batch in (1, 2):
        if strategy in ("loop", "calls"):
            assert stepper.parts.sizes(torchsim.State(*(x[:batch] for x in start))) == [1] * batch
        expected = _trajectory(reference, start, ctrl, batch)
        spread = _worst(expected, _trajectory(reference_per_component, start, ctrl, batch))
        got = _trajectory(stepper, start, ctrl, batch)
        worst = _worst(expected, got)
        moved = (expected[-1].x_pos - expected[0].x_pos).abs().max().item()
        print(f"{path.stem} {method} {strategy} batch {batch}: max |reference - {strategy}| {worst:.1e}, the "
              f"reference's own spread {spread:.1e}, over {STEPS} steps; bodies moved up to {moved:.2f} m")
        assert torch.equal(expected[-1].diverged, got[-1].diverged)
        assert moved > 1e-3
        assert worst <= max(1e-8, 10 * spread)
