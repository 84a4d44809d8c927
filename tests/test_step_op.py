"""The kernel strategy under ``torch.compile`` (``torchsim.execution.step_op``): a traced function around a Stepper
holds each physics step as one ``torchsim::step`` node, runs the same kernel, and reads the per-env parameters
as graph inputs. What the GPU's captured collector step is built on, checked on the CPU's C++ kernel."""

import warnings

import torch

import torchsim
import torchsim.envs


def graph_recorder():
    """A ``torch.compile`` backend that runs the FX graph as traced and keeps it (its nodes are what we check)."""
    graphs = []

    def backend(gm, example_inputs):
        graphs.append(gm)
        return gm.forward

    return backend, graphs


def step_nodes(gm) -> int:
    return sum(node.target in (torch.ops.torchsim.step, torch.ops.torchsim.step.default) for node in gm.graph.nodes)


def test_a_traced_stepper_is_one_operator_and_steps_as_the_kernel():
    sys_ = torchsim.load_mjcf(str(torchsim.envs.asset_path("inverted_double_pendulum.xml")))
    stepper = torchsim.Stepper(sys_)
    assert stepper.strategy == "kernel"
    torch.manual_seed(0)
    state = torchsim.init(sys_, sys_.q0 + 0.1 * torch.randn(5, sys_.nq), 0.1 * torch.randn(5, sys_.nv))
    ctrl = torch.rand(5, sys_.nu) * 2 - 1
    backend, graphs = graph_recorder()

    def two_steps(state, ctrl):
        return stepper(stepper(state, ctrl), -ctrl)

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # tracing the reference step would warn (pipeline.SLOW_COMPILE_WARNING)
        traced = torch.compile(two_steps, backend=backend, fullgraph=True)(state, ctrl)
    assert len(graphs) == 1 and step_nodes(graphs[0]) == 2
    assert len(graphs[0].graph.nodes) < 60  # the operator and the state's plumbing, not the step's ~1000 ops
    eager = two_steps(state, ctrl)
    for name, a, b in zip(torchsim.State._fields, traced, eager):
        assert torch.equal(a, b), name  # the same kernel on the same inputs
    assert not torch.equal(eager.q, state.q)


def test_a_compiled_env_advance_with_per_env_physics_equals_the_eager_one():
    """``TorchsimEnv._advance`` (physics, reward, termination; what a collector step runs) under inductor, with a
    different mass, friction and gain per env: the per-env parameters reach the kernel as graph inputs, so changing
    them after compiling changes the compiled step's result as it does the eager one's."""
    env = torchsim.envs.make("inverted_pendulum", num_envs=6, stepper="auto")
    env.reset()
    assert env.stepper.strategy == "kernel"
    torch.manual_seed(1)
    actions = torch.rand(8, 6, env.sys.nu) * 2 - 1
    compiled = torch.compile(env._advance)

    def rollout(advance):
        state, task, steps, out = env.state, env.task, env.step_count.clone(), []
        for action in actions:
            state, task, reward, terminated, truncated, steps = advance(state, task, env._ctrl(action), steps)
            out.append(torch.cat([state.q, state.qd, reward[:, None]], -1))
        return torch.stack(out)

    for masses in (torch.linspace(0.5, 1.5, 6), torch.linspace(2.0, 0.8, 6)):
        env.set_physics(mass_scale=masses, friction_scale=torch.linspace(0.5, 2.0, 6),
                        actuator_gain_scale=torch.linspace(0.7, 1.3, 6))
        eager = rollout(env._advance)
        assert torch.equal(rollout(compiled), eager)  # the kernel, between the same ops compiled or not
    assert not torch.equal(eager[:, 0], eager[:, -1])  # the envs differ
