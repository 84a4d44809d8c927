"""Row graphs (``torchsim.execution.kernel.rows``): the spring substep rewritten as ops on rows of envs gives the
substep's numbers.

Run eagerly here (building a row graph takes seconds); ``test_strategies.py`` runs the kernels generated from them.
Every shipped model's substep runs through the row-graph interpreter, so an op it does not cover shows here, not at
step time.
"""

import numpy as np
import pytest
import torch
import torch.utils._pytree as pytree

import torchsim
from models import ANT, F64, SHIPPED, load_model, random_q
from torchsim.execution.kernel import rows
from torchsim.kinematics import with_world
from torchsim.lanes import to_lanes
from torchsim.methods import METHODS

SPRING = METHODS["spring"]


def _substep_inputs(path, batch=3, seed=0):
    """A spring System and the flat lanes inputs of one substep: random poses (some below the floor, so contacts
    act), velocities and controls."""
    xml, m = load_model(path)
    sys = torchsim.load_mjcf(xml, dtype=F64)
    rng = np.random.default_rng(seed)
    q = torch.tensor(random_q(m, batch, rng))
    state = torchsim.init(sys, q, torch.tensor(rng.normal(0, 1, (batch, sys.nv))))
    bodies = with_world(*(to_lanes(x, 1) for x in state[:4]))
    ctrl = to_lanes(torch.tensor(rng.uniform(-1, 1, (batch, sys.nu)))).contiguous()
    h = sys.substep_timestep
    leaves, spec = pytree.tree_flatten((bodies, ctrl, SPRING.step_terms(sys, bodies, to_lanes(state.q), h)))
    return sys, leaves, spec, h


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.stem)
def test_row_graph_equals_substep(path):
    """Every shipped model (hinges, 3-hinge and free joints, slides, capsule/sphere/box contacts, contact-free arms):
    the spring substep runs through the row-graph interpreter, and the row graph's new poses equal the
    substep's to float64 rounding (the rewrite only reorders sums and folds constants)."""
    sys, leaves, spec, h = _substep_inputs(path)

    def substep(*flat):
        bodies, ctrl, terms = pytree.tree_unflatten(list(flat), spec)
        return tuple(SPRING.substep(sys, bodies, ctrl, terms, h))

    graph = rows.row_graph(substep, leaves)
    ops = {n.target for n in graph.graph.nodes if n.op == "call_function"}
    assert torch.ops.aten.index_select.default not in ops and torch.ops.aten.index_add.default not in ops
    # the compiled code receives every constant the graph holds: folding must not leave unused ones behind
    assert {name for name, _ in graph.named_buffers()} <= {n.target for n in graph.graph.nodes if n.op == "get_attr"}
    expected, got = substep(*leaves), graph(*leaves)
    worst = max((a - b).abs().max().item() for a, b in zip(expected, got))
    moved = max((a - b).abs().max().item() for a, b in zip(expected, leaves[:4]))
    print(f"{path.stem}: {len(graph.graph.nodes)} nodes, max |row graph - substep| {worst:.1e}, moved {moved:.1e}")
    assert moved > 1e-4 and worst < 1e-11


def test_one_row_graph_serves_every_batch():
    """A row graph reads its batch size from its inputs: built from 3 envs, it steps 5 and 2 others (inputs with
    one value for all envs, the last axis 1, stay so) to float64 rounding of the substep at those batches."""
    sys, leaves, spec, h = _substep_inputs(ANT, batch=3)

    def substep(*flat):
        bodies, ctrl, terms = pytree.tree_unflatten(list(flat), spec)
        return tuple(SPRING.substep(sys, bodies, ctrl, terms, h))

    graph = rows.row_graph(substep, leaves)
    for batch in (5, 2):
        _, others, other_spec, _ = _substep_inputs(ANT, batch=batch, seed=batch)
        assert other_spec == spec
        expected, got = substep(*others), graph(*others)
        assert all(x.shape[-1] == batch for x in got)
        assert max((a - b).abs().max().item() for a, b in zip(expected, got)) < 1e-11


def test_row_graphs_refuse_the_batch_axis():
    """Ops along the batch axis cannot be unrolled: a clear error, not a wrong graph."""
    with pytest.raises(NotImplementedError, match="batch axis"):
        rows.row_graph(lambda x: (x.sum(-1, keepdim=True).expand(3, 4),), [torch.ones(3, 4)])


def test_row_graphs_refuse_a_constant_that_differs_between_envs():
    """A row graph serves every batch size, so a value per env that no input holds (a constant made at the traced
    batch size) is refused by name; one that every env shares folds into the graph as a number."""
    with pytest.raises(NotImplementedError, match="constant with a batch axis"):
        rows.row_graph(lambda x: (x * torch.linspace(0, 1, x.shape[-1]),), [torch.ones(3, 4)])
    graph = rows.row_graph(lambda x: (x * torch.full((x.shape[-1],), 2.0),), [torch.ones(3, 4)])
    assert not [n for n in graph.graph.nodes if n.op == "get_attr"]
    torch.testing.assert_close(graph(torch.arange(15.0).view(3, 5)), (2 * torch.arange(15.0).view(3, 5),),
                               rtol=0, atol=0)
