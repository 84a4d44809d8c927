"""``torch.compile(torchsim.step, fullgraph=True)``: one graph, same numbers as eager (issue 2, item 9).

Compiling takes minutes per graph on 2 cores, so this file traces one small model (a hinged arm that hits the
floor, and a falling box; 2 substeps) with dynamo for both methods (one graph, no breaks) and compiles it with
inductor for the default method only, checking 20 steps against eager mode in float32; then twice more as
``compile_substeps`` runs it: as a row graph (the default for spring on CPU), and in parts on two threads.
"""

import pytest
import torch

import torchsim
from models import METHODS
from torchsim import parts, pipeline

MODEL = """
<mujoco><compiler angle="degree"/><option timestep="0.004"/><worldbody><geom type="plane" size="5 5 1"/>
  <body pos="0 0 0.6"><joint name="shoulder" type="hinge" axis="0 1 0" range="-100 100" damping="0.1" armature="0.01"/>
    <geom type="capsule" fromto="0 0 0 0.5 0 0" size="0.05"/>
    <body pos="0.5 0 0"><joint type="hinge" axis="0 1 0" range="-90 90"/>
      <geom type="capsule" fromto="0 0 0 0.4 0 0" size="0.04"/></body></body>
  <body pos="1 0 0.3"><freejoint/><geom type="box" size="0.1 0.1 0.1"/></body>
</worldbody><actuator><motor joint="shoulder" gear="5" ctrlrange="-1 1" ctrllimited="true"/></actuator></mujoco>"""


def _setup(method):
    sys = torchsim.load_mjcf(MODEL, method=method, substeps=2, dtype=torch.float32)
    batch = 8
    q = sys.q0.expand(batch, -1).clone()
    q[:, 0] = torch.linspace(-0.5, 0.5, batch)
    return sys, torchsim.init(sys, q, torch.zeros(batch, sys.nv)), torch.linspace(-1, 1, batch)[:, None]


@pytest.mark.parametrize("method", METHODS)
def test_step_traces_as_one_graph(method):
    torch._dynamo.reset()
    explanation = torch._dynamo.explain(torchsim.step)(*_setup(method))
    assert explanation.graph_break_count == 0, explanation.break_reasons
    assert explanation.graph_count == 1


def test_compiled_step_matches_eager(method="spring"):
    torch._dynamo.reset()
    sys, state, ctrl = _setup(method)
    compiled = torch.compile(torchsim.step, fullgraph=True)
    # One step from each state of a 20-step trajectory (free fall, the arm hitting the floor, the box landing):
    # the compiled step must equal the eager step to 1e-5 in float32 (fused kernels reorder float32 arithmetic;
    # over many steps the differences would grow with the dynamics' sensitivity, which is not what is tested).
    worst = dict.fromkeys(("x_pos", "x_quat", "xd_vel", "q"), 0.0)
    for _ in range(20):
        eager_next = torchsim.step(sys, state, ctrl)
        compiled_next = compiled(sys, state, ctrl)
        for name in worst:
            diff = (getattr(eager_next, name) - getattr(compiled_next, name)).abs().max().item()
            worst[name] = max(worst[name], diff)
        assert torch.equal(eager_next.diverged, compiled_next.diverged)
        state = eager_next
    print(f"{method}: max |eager - compiled| per step {worst}")
    assert max(worst["x_pos"], worst["x_quat"], worst["q"]) < 1e-5
    assert worst["xd_vel"] < 1e-5
    assert not state.diverged.any()


def _compiled_steps(sys, state, ctrl, steps=5, **options):
    """``steps`` steps under ``compile_substeps(**options)`` (the first compiles), and the number of graphs
    dynamo compiled for them."""
    torch.compiler.reset()
    pipeline._ROW_GRAPHS.clear()
    torchsim.compile_substeps(**options)
    graphs = torch._dynamo.utils.counters["stats"]["unique_graphs"]
    try:
        compiled = [state]
        with torch.no_grad():  # as collectors step envs
            for _ in range(steps):
                compiled.append(torchsim.step(sys, compiled[-1], ctrl))
    finally:
        torchsim.compile_substeps(False)
    return compiled, torch._dynamo.utils.counters["stats"]["unique_graphs"] - graphs


def _worst_vs_eager(sys, compiled, ctrl):
    eager = [compiled[0]]
    for _ in compiled[1:]:
        eager.append(torchsim.step(sys, eager[-1], ctrl))
    assert not compiled[-1].diverged.any()
    return max((a - b).abs().max().item() for e, c in zip(eager, compiled) for a, b in zip(e[:6], c[:6]))


def test_compiled_row_graph_matches_eager(method="spring"):
    """``compile_substeps()`` as the benchmarks run it on CPU: the step's terms and end compiled by dynamo (two
    graphs), the substep as a row graph (``torchsim.rows``) compiled by inductor alone and called once per
    substep. Same numbers as the eager step; the row graph is built once for all five steps."""
    sys, state, ctrl = _setup(method)
    compiled, graphs = _compiled_steps(sys, state, ctrl)
    assert graphs == 2 and len(pipeline._ROW_GRAPHS) == 1
    worst = _worst_vs_eager(sys, compiled, ctrl)
    print(f"{method}: max |eager - compiled row graph| over 5 steps {worst:.2e}")
    assert worst < 1e-4  # float32 rounding, grown over 5 steps (one step: 1e-5, test above)


def test_compiled_parts_on_threads_match_eager(method="spring"):
    """``compile_substeps(rows=False)``: the compiled step (its substeps one loop), the batch cut into parts that two
    threads step at once (``torchsim.parts``; 4 parts of 2 here), joined. Same numbers as one eager whole-batch
    step."""
    sys, state, ctrl = _setup(method)
    parts.PARTS.set(2, 2)
    assert parts.part_sizes(state) == [2, 2, 2, 2]
    # the first step compiles (parts one after another), the others run on two threads
    compiled, graphs = _compiled_steps(sys, state, ctrl, part_size=2, workers=2, rows=False)
    assert graphs == 1  # the step, its substeps a loop
    worst = _worst_vs_eager(sys, compiled, ctrl)
    print(f"{method}: max |eager - compiled in parts| over 5 steps {worst:.2e}")
    assert worst < 1e-4


def test_steps_recording_gradients_run_eagerly(method="spring"):
    """After ``compile_substeps``, a step that autograd records runs eagerly (warned once): its gradients are the
    eager step's, not the compiled loop's (``while_loop`` gave wrong ones in torch 2.13). Nothing compiles."""
    sys, state, ctrl = _setup(method)
    sys = sys.replace(body_mass=sys.body_mass.clone().requires_grad_())
    (eager_grad,) = torch.autograd.grad(torchsim.step(sys, state, ctrl).x_pos[:, :, 2].sum(), sys.body_mass)
    torchsim.compile_substeps(part_size=0)
    pipeline._warn_eager_for_grad.cache_clear()
    graphs = torch._dynamo.utils.counters["stats"]["unique_graphs"]
    try:
        with pytest.warns(UserWarning, match="requires grad"):
            moved = torchsim.step(sys, state, ctrl).x_pos
    finally:
        torchsim.compile_substeps(False)
    (grad,) = torch.autograd.grad(moved[:, :, 2].sum(), sys.body_mass)
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] == graphs
    assert torch.equal(grad, eager_grad) and grad.abs().sum() > 0
