"""A whole step as one generated C++ function: ``torchsim.step`` for a System whose parameters every env shares.

The step is three row graphs (``torchsim.rows``) of the reference pipeline's own functions, chained by
``torchsim.row_code`` into one function that reads the public state and controls and writes the next state:

1. the method's step terms, from the poses at the step's start (the terms every env shares fold into the substep
   as constants; the per-env ones are rows);
2. the substep, repeated ``sys.substeps`` times on rows that stay in registers and on the stack;
3. ``pipeline.finish_lanes``: ``q, qd`` read back, divergence contained.

A step is then one call from Python, at any batch size; its build takes seconds where inductor's compile of the
substep alone takes minutes (``docs/benchmarks.md``). The built library is kept on disk (``torchsim.row_cache``):
a later process with the same model, dtype, torch and torchsim source loads it in milliseconds.
"""

import torch
import torch.utils._pytree as pytree

from torchsim import lanes, pipeline, progress, row_cache, row_code, rows
from torchsim.kinematics import Bodies, with_world
from torchsim.methods import METHODS
from torchsim.state import State
from torchsim.system import System


def join_poses(bodies: Bodies) -> torch.Tensor:
    """The lanes tensors of ``bodies`` as the rows of one ``(rows, B)`` tensor; :func:`split_poses` undoes it."""
    return torch.cat([x.reshape(-1, x.shape[-1]) for x in bodies])


def split_poses(poses: torch.Tensor, shapes: list) -> list[torch.Tensor]:
    return [x.view(*shape[:-1], poses.shape[-1])  # the batch size of poses: row graphs trace at another
            for x, shape in zip(poses.split([shape[:-1].numel() for shape in shapes]), shapes)]


class StepKernel:
    """``torchsim.step(sys, state, ctrl)`` as one generated C++ function, built for ``sys``'s values and dtype on
    CPU; ``threads`` threads share each batch. Raises ``rows.Unsupported`` when the step cannot be expressed."""

    def __init__(self, sys: System, threads: int = 1):
        if sys.device.type != "cpu" or sys.batched:
            raise rows.Unsupported("a step kernel runs on CPU, with parameters shared by every env")
        self.sys = sys
        # traced at two copies of the model's rest state: only shapes matter, and which terms are per env
        state = pipeline.init(sys, sys.q0.expand(2, -1).contiguous(), torch.zeros(2, sys.nv, dtype=sys.dtype))
        ctrl = torch.zeros(2, sys.nu, dtype=sys.dtype)
        inputs = [*pipeline.to_lanes_state(state), lanes.to_lanes(ctrl)]
        key = row_cache.content_key(sys, inputs, {"step kernel": row_code.compiler_command()})
        path = row_code.library_path(key)
        what = f"the {sys.method} step ({sys.num_bodies} bodies, {sys.dtype})"
        if path.is_file():
            progress.log.info("loaded %s from %s", what, path)
        else:
            layouts = [row_code.Tensor.of(x) for x in inputs]
            with progress.announce(f"{what}: tracing its row graphs"):
                graphs = self._graphs(state, ctrl)
            program = self._wire(row_code.Program(sys.dtype, layouts, layouts[:7]), *graphs)
            path = row_code.build(program.source(), what, key)
        self.kernel = row_code.Kernel(path, sys.dtype, threads)
        self.fields = [(x.shape[1:], x.dtype) for x in (*state, ctrl)]

    def _graphs(self, state: State, ctrl: torch.Tensor):
        sys, h = self.sys, self.sys.substep_timestep
        method = METHODS[sys.method]
        bodies = with_world(*(lanes.to_lanes(x, 1) for x in state[:4]))
        shapes = [x.shape for x in bodies]
        poses = join_poses(bodies)
        leaves, spec = pytree.tree_flatten(method.step_terms(sys, bodies, h))
        per_env = [i for i, x in enumerate(leaves) if lanes.per_env(x)]

        def terms(poses):
            found = pytree.tree_flatten(method.step_terms(sys, Bodies(*split_poses(poses, shapes)), h))[0]
            return tuple(found[i] for i in per_env)

        def substep(poses, ctrl, *per_env_terms):
            step_terms = list(leaves)  # the terms every env shares: constants of the graph
            for i, x in zip(per_env, per_env_terms):
                step_terms[i] = x
            after = method.substep(sys, Bodies(*split_poses(poses, shapes)), ctrl,
                                   pytree.tree_unflatten(step_terms, spec), h)
            return (join_poses(after),)

        def finish(*old_and_poses):
            old = State(*old_and_poses[:7])
            return tuple(pipeline.finish_lanes(sys, old, Bodies(*split_poses(old_and_poses[7], shapes))))

        lanes_ctrl = lanes.to_lanes(ctrl).contiguous()
        graphs = (rows.row_graph(terms, [poses]),
                  rows.row_graph(substep, [poses, lanes_ctrl, *(leaves[i] for i in per_env)]),
                  rows.row_graph(finish, [*(x.contiguous() for x in pipeline.to_lanes_state(state)), poses]))
        # where each pose row starts a step: a row of the state (input t, its lanes row), or the world body's
        carried = []
        n = sys.num_bodies
        for t, x in enumerate(bodies):
            for c in range(x.shape[0]):
                carried += [("input", t, c * n + b) for b in range(n)]
                carried.append(("value", 1.0 if (t == 1 and c == 0) else 0.0))  # the world: at rest, identity
        return graphs, carried

    @staticmethod
    def _wire(program: row_code.Program, graphs, carried) -> row_code.Program:
        terms_graph, substep_graph, finish_graph = graphs
        start = [program.input_row(*c[1:]) if c[0] == "input" else c[1] for c in carried]
        terms = program.add(terms_graph, [lambda r: ("value", start[r])])
        rows_now = program.loop(start)
        after = program.add(substep_graph, [lambda r: ("value", rows_now[r]), lambda r: ("input", 7, r)]
                            + [lambda r, k=k: ("value", terms[k][r]) for k in range(len(terms))])
        program.end_loop(after[0])
        new = program.add(finish_graph, [lambda r, t=t: ("input", t, r) for t in range(7)]
                          + [lambda r: ("value", rows_now[r])])
        for k, field in enumerate(new):
            program.store(k, field)
        return program

    def __call__(self, state: State, ctrl: torch.Tensor) -> State:
        names = [f"state.{field}" for field in State._fields] + ["ctrl"]
        for name, x, (shape, dtype) in zip(names, (*state, ctrl), self.fields):
            if x.shape[1:] != shape or x.dtype != dtype or x.device.type != "cpu":  # the code reads raw memory
                raise ValueError(f"{name} must be a CPU {dtype} tensor of shape (B, {', '.join(map(str, shape))})"
                                 f" for this System's step kernel, got {x.dtype} {tuple(x.shape)} on {x.device}")
        inputs = [x.contiguous() for x in (*state, ctrl)]
        outputs = [torch.empty_like(x) for x in inputs[:7]]
        self.kernel(ctrl.shape[0], inputs, outputs, self.sys.substeps)
        return State(*outputs)
