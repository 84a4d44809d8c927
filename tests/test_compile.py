"""``torch.compile(torchsim.step, fullgraph=True)``: one graph, same numbers as eager.

Compiling takes minutes per graph on 2 cores, so this file traces one small model (a hinged arm that hits the
floor, and a falling box; 2 substeps) with dynamo for both methods (one graph, no breaks) and compiles it with
inductor for the default method only (1 substep), checking 20 steps against eager mode in float32; then twice more as
``torchsim.Stepper`` runs it: as a generated C++ step (the default for spring on CPU), and as the compiled step it
falls back to, in parts on two threads. Steppers of different strategies step side by side in one process.
"""

import functools

import pytest
import torch

import torchsim
from models import METHODS
from torchsim.execution import strategies
from torchsim.execution.kernel import rows

MODEL = """
<mujoco><compiler angle="degree"/><option timestep="0.004"/><worldbody><geom type="plane" size="5 5 1"/>
  <body pos="0 0 0.6"><joint name="shoulder" type="hinge" axis="0 1 0" range="-100 100" damping="0.1" armature="0.01"/>
    <geom type="capsule" fromto="0 0 0 0.5 0 0" size="0.05"/>
    <body pos="0.5 0 0"><joint type="hinge" axis="0 1 0" range="-90 90"/>
      <geom type="capsule" fromto="0 0 0 0.4 0 0" size="0.04"/></body></body>
  <body pos="1 0 0.3"><freejoint/><geom type="box" size="0.1 0.1 0.1"/></body>
</worldbody><actuator><motor joint="shoulder" gear="5" ctrlrange="-1 1" ctrllimited="true"/></actuator></mujoco>"""


def _setup(method, substeps=2):
    sys = torchsim.load_mjcf(MODEL, method=method, substeps=substeps, dtype=torch.float32)
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
    # One substep: inductor builds the step with its substeps unrolled, and a second copy of the same substep
    # checks nothing new while it costs a third more build time (96 s against 69 s on a loaded CI core).
    sys, state, ctrl = _setup(method, substeps=1)
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


def _compiled_steps(stepper, state, ctrl, steps=5):
    """``steps`` steps of ``stepper`` (the first compiles), and the number of graphs dynamo compiled for them."""
    graphs = torch._dynamo.utils.counters["stats"]["unique_graphs"]
    compiled = [state]
    with torch.no_grad():  # as collectors step envs
        for _ in range(steps):
            compiled.append(stepper(compiled[-1], ctrl))
    return compiled, torch._dynamo.utils.counters["stats"]["unique_graphs"] - graphs


def _worst_vs_eager(sys, compiled, ctrl):
    eager = [compiled[0]]
    for _ in compiled[1:]:
        eager.append(torchsim.step(sys, eager[-1], ctrl))
    assert not compiled[-1].diverged.any()
    return max((a - b).abs().max().item() for e, c in zip(eager, compiled) for a, b in zip(e[:6], c[:6]))


def test_kernel_and_fallback_steppers_match_eager_side_by_side(tmp_path, monkeypatch, method="spring"):
    """Two steppers of one System in one process, stepped in turn. One runs ``kernel`` (the default on CPU: the
    whole step one generated C++ function, built once). The other is asked for the default too, but the row
    interpreter is made to lack ``torch.cat``, so the kernel cannot express the step: it falls back, with one
    warning naming the op, to ``loop`` (the step one compiled graph, its substeps a loop; the batch cut into 4 parts
    of 2 that two threads step at once, joined; its graph run by ``aot_eager``: inductor's code for it is checked
    above). Each gives the eager step's numbers."""
    monkeypatch.setenv("TORCHSIM_CACHE_DIR", str(tmp_path))  # a kernel stored by an earlier run would load
    torch.compiler.reset()
    sys, state, ctrl = _setup(method)
    looped = torchsim.Stepper(sys, part_size=2, threads=2, backend="aot_eager")
    with monkeypatch.context() as patch:
        patch.delattr(rows._RowOps, "_op_cat_default")
        with pytest.warns(UserWarning) as warned:
            looped_states, _ = _compiled_steps(looped, state, ctrl, steps=1)
    messages = [str(w.message) for w in warned if "cannot run as the" in str(w.message)]
    assert [m.split(" strategy (")[0].split()[-1] for m in messages] == ["kernel"], messages
    assert "row graphs do not support aten.cat" in messages[0] and "using the loop strategy" in messages[0]
    kernel = torchsim.Stepper(sys)
    kernel_states, _ = _compiled_steps(kernel, state, ctrl, steps=1)
    assert (kernel.strategy, looped.strategy) == ("kernel", "loop")
    assert looped.parts.sizes(state) == [2, 2, 2, 2]
    steppers = {"kernel": (kernel, kernel_states), "loop": (looped, looped_states)}
    graphs = dict.fromkeys(steppers, 0)
    for _ in range(4):  # alternating: neither stepper's compiled code disturbs the other's, nothing recompiles
        for name, (stepper, states) in steppers.items():
            more, new_graphs = _compiled_steps(stepper, states[-1], ctrl, steps=1)
            states.append(more[-1])
            graphs[name] += new_graphs
    assert graphs == dict.fromkeys(steppers, 0) and kernel.num_kernels == 1
    for name, (_, states) in steppers.items():
        worst = _worst_vs_eager(sys, states, ctrl)
        print(f"{method}: max |eager - {name} stepper| over {len(states) - 1} steps {worst:.2e}")
        assert worst < 1e-4  # float32 rounding, grown over 5 steps (one step: 1e-5, test above)


def test_steps_recording_gradients_run_compiled(method="spring"):
    """A compiled stepper steps a rollout that autograd records through compiled code with a backward (not the
    ``loop`` strategy's ``while_loop``, whose gradients came out wrong in torch 2.13): gradients with respect to the
    initial velocities, the controls and the masses equal the reference step's to float rounding over 3 steps. It
    compiles once; a second rollout compiles nothing. Inductor's code for a forward and backward of this model takes
    ~5 min to build on a CI core, so the stepper here compiles through ``aot_eager`` (the same dynamo graphs and
    AOTAutograd split into forward and backward, run as ATen ops); inductor's gradients are checked against the
    eager step's on the Ant by ``studies/grad_horizon.py speed --stepper compiled`` (docs/gradients.md)."""
    sys, state, ctrl = _setup(method)
    mass = sys.body_mass.clone().requires_grad_()
    sys = sys.replace(body_mass=mass)
    stepper = torchsim.Stepper(sys, "loop", part_size=0, backend="aot_eager")

    def gradients(step):
        qd0, controls = state.qd.clone().requires_grad_(), ctrl.expand(3, -1, -1).clone().requires_grad_()
        s = torchsim.init(sys, state.q, qd0)
        for c in controls:
            s = step(s, c)
        objective = s.x_pos[:, :, 2].sum() + s.qd.square().sum()
        return torch.autograd.grad(objective, (qd0, controls, mass))

    eager = gradients(functools.partial(torchsim.step, sys))
    graphs = torch._dynamo.utils.counters["stats"]["unique_graphs"]
    compiled = gradients(stepper)
    # one substep and one step end, though the first step starts from positions that require no grad
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] == graphs + 2
    again = gradients(stepper)
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] == graphs + 2
    for name, want, got, got_again in zip(("qd0", "ctrl", "mass"), eager, compiled, again):
        # float32: fused kernels reorder the arithmetic (one step: 1e-5 on the state, test_compiled_step_...)
        error = ((got - want).abs().max() / want.abs().max()).item()
        print(f"d objective / d {name}: max |compiled - eager| / max |eager| = {error:.1e}")
        assert want.abs().max() > 0 and error < 1e-4, name
        assert torch.equal(got, got_again)


def test_strategy_selection():
    """``auto`` takes the first strategy of the table for the System's method and device: the C++ step kernel for
    spring on CPU (per-env parameters included: they are the kernel's inputs) and compiled calls for xpbd; a
    strategy the table does not list for the System is refused naming those it does (nothing compiles here)."""
    spring = torchsim.load_mjcf(MODEL, method="spring", substeps=2)
    batched = spring.replace(body_mass=spring.body_mass.expand(3, -1))
    xpbd = torchsim.load_mjcf(MODEL, method="xpbd", substeps=2)
    assert [torchsim.Stepper(s).strategy for s in (spring, batched, xpbd)] == ["kernel", "kernel", "calls"]
    assert strategies(spring) == ("kernel", "loop", "eager") and strategies(xpbd) == ("calls", "eager")
    assert torchsim.Stepper(spring, "eager").strategy == "eager"
    with pytest.raises(ValueError, match=r"the xpbd method on cpu runs as \('calls', 'eager'\)"):
        torchsim.Stepper(xpbd, "loop")
    with pytest.raises(ValueError, match="unknown strategy 'rows'"):
        torchsim.Stepper(spring, "rows")
    # new per-env parameters (set_physics at a reset) keep the stepper's parts: their threads, and which part sizes
    # have compiled, so the next step runs on every thread at once
    looped = torchsim.Stepper(batched, "loop", threads=2)
    redrawn = looped.for_system(spring.replace(body_mass=spring.body_mass.expand(3, -1) * 1.1))
    assert redrawn.strategy == "loop" and redrawn.parts is looped.parts
