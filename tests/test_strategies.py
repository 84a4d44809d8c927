"""Every strategy a ``torchsim.Stepper`` runs agrees with the reference step (``torchsim.step``) on the models the
envs ship: spring through ``kernel`` (the generated C++) and ``loop``, xpbd through ``calls``; 20 steps, at batch 1
and at a batch of two cut into two parts of one env, which two threads step at once. And the GPU kernel (the same
step Program emitted as CUDA C) on every shipped model, its source compiled for the host CPU (a loop over envs in
place of the grid).

In float64, against the reference's own rounding: a strategy evaluates the step with other formulas for a few
primitives (the per-component forms that ``torch.compile`` and row graphs trace, ``torchsim.spatial``) and the row
graph also reorders sums and folds constants. Where large spring forces nearly cancel, float64 rounding is amplified:
in one Pusher start, cross products of terms of size ~1e12 differ by 2^-11 between the two formulas, which moves the
next state by 1e-3. So each case first measures the reference's own spread (``torchsim.step`` with its eager
formulas against ``torchsim.step`` with the per-component ones, same starts and controls) and bounds the strategy's
difference from the reference by 10x that spread, and at least 1e-8 (the spread is 1e-18 to 2e-10 in the calm
starts; float32 rounding alone moves velocities by ~1e-3 m/s in a step of the stiff springs, so float32 would hide
errors of that size).

``loop`` and ``calls`` run with the ``eager`` backend (``Stepper(..., backend=...)``): their own graphs (dynamo's
graph of the whole step with its ``while_loop``; the separate substep and step end), substep loop and parts,
executed op by op (inductor's code generation for them takes minutes per model on two cores; it is checked in
float32 on a small model in ``test_compile.py``). CI runs five models that between them hold every joint kind,
contact shape and loader (the Ant: free root and hinges, capsule and sphere contacts; the Humanoid: 2- and 3-hinge
joints; the Hopper: slides; Fetch: boxes; the UR5e: a URDF arm without contacts), the CUDA kernel all twelve.
``TORCHSIM_TEST_ALL_MODELS=1`` runs every shipped model and strategy, and ``TORCHSIM_TEST_BACKEND=inductor`` the
generated code of ``loop`` and ``calls`` (about five minutes of compiling per model).
"""

import os

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from torchsim import spatial
from torchsim.execution.kernel import emit_cuda
from torchsim.execution.kernel.step import StepKernel
from models import SHIPPED, load_model, random_q

BACKEND = os.environ.get("TORCHSIM_TEST_BACKEND", "eager")
ALL_MODELS = bool(os.environ.get("TORCHSIM_TEST_ALL_MODELS"))
CI_MODELS = ("ant", "humanoid", "hopper", "fetch", "ur5e")
CASES = [("spring", "kernel"), ("spring", "loop"), ("xpbd", "calls")]
# a model's C++ kernel and its CUDA kernel on one xdist worker (``--dist loadgroup``): the second emits from the
# step Program the first traced (``execution.kernel.step``) instead of tracing it again
PARAMS = [pytest.param(path, method, strategy, id=f"{path.stem}-{method}-{strategy}",
                       marks=[pytest.mark.xdist_group(path.stem)] if strategy == "kernel" else [])
          for path in SHIPPED if ALL_MODELS or path.stem in CI_MODELS for method, strategy in CASES]
STEPS = 20


def _start(path, method: str, batch: int, contact_model: str = "impulse"):
    """The model in float64; ``batch`` starts with hinges within 0.1 rad of their initial angle and slides up to 5 cm
    above their initial value (in their range), ball joints and free bodies in a random orientation, free bodies
    0.1 m above their initial position (so bodies fall, tumble and land: contacts act within the 20 steps), random
    velocities; random controls within 30% of the control range's half-width.

    Grasp's claw starts around its ball here (the env starts it 6 m above): the ball is flung, and Grasp's spring
    model (the env ships xpbd: ``envs/targets.py``) diverges within 20 steps. The engine then freezes the env at its
    last good state, so a strategy must flag the same envs and agree on the steps before."""
    xml, m = load_model(path)
    sys = torchsim.load_mjcf(xml, method=method, dtype=torch.float64, contact_model=contact_model)
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
        for t in range(len(ctrl)):
            states.append(step(states[-1], ctrl[t, :batch]))
    return states


def _worst(states_a: list, states_b: list) -> float:
    return max((a - b).abs().max().item() for sa, sb in zip(states_a, states_b) for a, b in zip(sa[:6], sb[:6]))


@pytest.mark.parametrize("path,method,strategy", PARAMS)
def test_strategy_agrees_with_reference(path, method, strategy):
    sys, start, ctrl = _start(path, method, batch=2)
    stepper = torchsim.Stepper(sys, strategy, part_size=1, threads=2, backend=BACKEND)
    assert stepper.strategy == strategy
    for batch in (1, 2):
        if strategy in ("loop", "calls"):
            assert stepper.parts.sizes(torchsim.State(*(x[:batch] for x in start))) == [1] * batch
        _check_against_reference(f"{path.stem} {method} {strategy} batch {batch}", sys, stepper, start, ctrl, batch,
                                 min_move=1e-3)


FREE_BODIES = """
<mujoco>
  <worldbody>
    <geom type="plane" size="5 5 0.1"/>
    <body pos="0 0 0.3"><freejoint/><geom type="box" size="0.1 0.05 0.08"/></body>
    <body pos="0.5 0 0.3" euler="0 30 0"><freejoint/><geom type="capsule" size="0.05 0.1"/></body>
  </worldbody>
</mujoco>
"""


def test_a_model_of_free_bodies_alone_runs_on_the_kernel():
    """No hinge or slide anywhere: the step's joint-space rows are empty, and the kernel holds none of them (it
    used to refuse such a model and fall back to ``loop``)."""
    sys = torchsim.load_mjcf(FREE_BODIES, dtype=torch.float64)
    generator = torch.Generator().manual_seed(0)
    start = torchsim.init(sys, sys.q0.expand(2, -1).clone(),
                          torch.randn(2, sys.nv, generator=generator, dtype=torch.float64))
    stepper = torchsim.Stepper(sys, "kernel")
    ctrl = torch.zeros(STEPS * 5, 2, 0, dtype=torch.float64)  # 0.2 s: both land
    _check_against_reference("free bodies kernel", sys, stepper, start, ctrl, 2, min_move=0.05)
    assert stepper.strategy == "kernel"


def _check_against_reference(what: str, sys, step, start, ctrl, batch: int, min_move: float) -> None:
    """``step`` from ``start`` under ``ctrl`` against the reference step, within 10x the reference's own spread
    (at least 1e-8), the same envs flagged diverged, and the bodies moving at least ``min_move`` [m]."""
    def reference_per_component(state, ctrl):
        with spatial.component_formulas():
            return torchsim.step(sys, state, ctrl)

    expected = _trajectory(lambda state, ctrl: torchsim.step(sys, state, ctrl), start, ctrl, batch)
    spread = _worst(expected, _trajectory(reference_per_component, start, ctrl, batch))
    got = _trajectory(step, start, ctrl, batch)
    worst = _worst(expected, got)
    moved = (expected[-1].x_pos - expected[0].x_pos).abs().max().item()
    print(f"{what}: max |reference - it| {worst:.1e}, the reference's own spread {spread:.1e}, over {len(ctrl)} "
          f"steps; bodies moved up to {moved:.2e} m")
    assert torch.equal(expected[-1].diverged, got[-1].diverged)
    assert moved > min_move
    assert worst <= max(1e-8, 10 * spread)


@pytest.mark.parametrize("path", [pytest.param(p, marks=pytest.mark.xdist_group(p.stem)) for p in SHIPPED],
                         ids=lambda p: p.stem)
def test_gpu_kernel_agrees_with_reference(path, monkeypatch, tmp_path):
    """The step Program emitted as CUDA C, as a GPU runs it (one thread an env, one launch a step), its source
    compiled for the host: float64 steps of 2 envs against the reference by the bound above."""
    monkeypatch.setenv("TORCHSIM_CACHE_DIR", str(tmp_path))
    sys, start, ctrl = _start(path, "spring", batch=2)
    kernel = StepKernel(sys, emitter=emit_cuda)
    assert "__global__ void step(" in next((tmp_path / "cuda").glob("*.cu")).read_text()
    _check_against_reference(f"{path.stem} cuda (host build)", sys, lambda state, ctrl: kernel(sys, state, ctrl),
                             start, ctrl, 2, min_move=1e-3)


# A free torso on two hinged legs whose feet land and slide within the test's steps (from step 11 on; some
# points push along their pyramid's edges, so the pyramid solve releases edges): the articulated step's every part
# at a fraction of the Ant's generated code (5 contact points' 20 pyramid edges against the Ant's 32).
BIPED = """
<mujoco>
  <option timestep="0.01"/>
  <worldbody>
    <geom type="plane" size="5 5 0.1"/>
    <body pos="0 0 0.05">
      <freejoint/>
      <geom type="sphere" size="0.08"/>
      <body name="l"><joint name="left" type="hinge" axis="0 1 0" range="-60 60"/>
        <geom type="capsule" fromto="0 0 0 0.15 0 -0.16" size="0.03"/></body>
      <body name="r"><joint name="right" type="hinge" axis="1 0 0" range="-60 60"/>
        <geom type="capsule" fromto="0 0 0 0 0.15 -0.16" size="0.03"/></body>
    </body>
  </worldbody>
  <contact><exclude body1="l" body2="r"/></contact>
  <actuator>
    <motor joint="left" ctrlrange="-1 1" gear="5"/>
    <motor joint="right" ctrlrange="-1 1" gear="5"/>
  </actuator>
</mujoco>
"""


def test_articulated_contacts_agree_on_both_kernels(monkeypatch, tmp_path):
    """A free body on hinges on ``contact_model="articulated"`` (the tree's columns and solves, the pyramid's
    pivoting solve) through the C++ kernel and the CUDA kernel's host build, by the bound above."""
    monkeypatch.setenv("TORCHSIM_CACHE_DIR", str(tmp_path))
    (tmp_path / "biped.xml").write_text(BIPED)
    sys, start, ctrl = _start(tmp_path / "biped.xml", "spring", 2, "articulated")
    _check_against_reference("biped articulated kernel", sys, torchsim.Stepper(sys, "kernel", threads=2), start, ctrl,
                             2, min_move=1e-3)
    kernel = StepKernel(sys, emitter=emit_cuda)
    _check_against_reference("biped articulated cuda (host build)", sys, lambda state, ctrl: kernel(sys, state, ctrl),
                             start, ctrl, 2, min_move=1e-3)
