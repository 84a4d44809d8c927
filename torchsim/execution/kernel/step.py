"""A whole step as one generated kernel: ``torchsim.step`` for a spring System, its per-env parameters inputs of
the kernel and its shared ones constants in it; C++ on a CPU (``emit_cpp``), CUDA C on a GPU (``emit_cuda``).

The step is three row graphs (``rows``) of the reference pipeline's own phases, chained into one
:class:`~torchsim.execution.kernel.program.Program` that reads the public state and controls and writes the next
state:

1. the method's step terms, from the poses and coordinates at the step's start (the terms every env shares fold
   into the substep as constants; the per-env ones are rows);
2. the substep, repeated ``sys.substeps`` times on rows that stay in registers;
3. ``pipeline.finish_lanes``: ``q, qd`` read back, divergence contained.

A step is then one call from Python (one launch on a GPU), at any batch size; its C++ build takes seconds where
inductor's compile of the substep alone takes minutes (``docs/benchmarks.md``). The built code is kept on disk
(``cache``): a later process with the same model, dtype, torch and torchsim source loads it in milliseconds.
"""

import hashlib

import torch
import torch.utils._pytree as pytree

from torchsim import lanes, pipeline, progress
from torchsim.execution.kernel import cache, emit_cpp, emit_cuda, rows
from torchsim.execution.kernel.program import Layout, Program
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


#: The State's fields a kernel steps: all but ``act``, which the Systems it runs (without activation dynamics) hold
#: empty; a System with activations is refused (the ``loop`` strategy runs it).
STEPPED = State._fields.index("act")


#: The code generator for each device type: its module has ``source(program)``, ``path(key)``,
#: ``build(code, what, key)`` and ``Kernel(path, dtype, device, **options)``.
EMITTERS = {"cpu": emit_cpp, "cuda": emit_cuda}


#: The Programs this process traced, by what they depend on (the last 32): a second code generator for the same
#: step (the CPU's and a GPU's kernel in one process) emits from the Program instead of tracing it again.
_PROGRAMS: dict[str, Program] = {}


class StepKernel:
    """``torchsim.step(sys, state, ctrl)`` as one generated kernel for Systems like ``sys`` on its device: its shared
    parameters' values are built in, its per-env parameters (``set_physics``) are inputs, so a System with other
    per-env values (``kernel(other_sys, state, ctrl)``) runs on the same code. ``emitter``: the code generator
    (default: the device's, :data:`EMITTERS`; ``emit_cuda`` for a CPU System compiles the GPU code for the host,
    to check it); ``options`` go to its ``Kernel`` (C++: ``threads`` that share each batch; CUDA: ``block``).
    Raises ``rows.Unsupported`` when the step cannot be expressed."""

    def __init__(self, sys: System, emitter=None, **options):
        emitter = emitter or EMITTERS.get(sys.device.type)
        if emitter is None:
            raise rows.Unsupported(f"no step kernel is generated for {sys.device.type} devices")
        if sys.na:
            raise rows.Unsupported(f"the step kernel does not carry actuator activations (State.act: the model has "
                                   f"{sys.na} activation states)")
        if sys.hfield_windows:
            raise rows.Unsupported("the step kernel does not collide height fields (hfield geoms: their cells are "
                                   "gathered by index, torchsim.collision_hfield)")
        self.substeps, self.device = sys.substeps, sys.device
        # traced on the CPU (the row interpreter reads index tensors as NumPy arrays; the Program it makes does not
        # depend on the device), at two envs (env 0's per-env parameters, the model's rest state): only shapes
        # matter, and which terms are per env
        sys = sys.to(device="cpu")
        self.where = sys.per_env_parameters()
        per_env = [sys.parameter(w) for w in self.where]
        probe_sys = sys.with_parameters(self.where, [x[:1].expand(2, *x.shape[1:]).contiguous() for x in per_env])
        q0 = sys.q0.expand(2, -1).contiguous()
        state = pipeline.init(probe_sys, q0, torch.zeros(2, sys.nv, dtype=sys.dtype))
        ctrl = torch.zeros(2, sys.nu, dtype=sys.dtype)
        params = [lanes.to_lanes(probe_sys.parameter(w)) for w in self.where]
        inputs = [*pipeline.to_lanes_state(state)[:STEPPED], lanes.to_lanes(ctrl), *params]
        # the key holds the shared parameters' values and the per-env ones' shapes (their values are inputs)
        shapes_only = sys.with_parameters(self.where, [x.new_zeros(x.shape[1:]) for x in per_env])
        step_key = cache.content_key(shapes_only, inputs, {}, self.where)  # what the Program depends on
        key = hashlib.sha256(repr((step_key, emitter.settings())).encode()).hexdigest()[:32]  # and its code
        path = emitter.path(key)
        what = f"the {sys.method} step ({sys.num_bodies} bodies, {sys.dtype}" + (
            f", {len(self.where)} per-env parameters)" if self.where else ")")
        if cache.verified(path):
            progress.log.info("loaded %s from %s", what, path)
        else:
            program = _PROGRAMS.get(step_key)
            if program is None:
                layouts = [Layout.of(x) for x in inputs]
                with progress.announce(f"{what}: tracing its row graphs"):
                    graphs = _graphs(probe_sys, self.where, state, ctrl, params)
                program = _wire(Program(sys.dtype, layouts, layouts[:7]), *graphs, len(params))
                _PROGRAMS[step_key] = program
                while len(_PROGRAMS) > 32:  # a few MB each (the Humanoid's ~20k statements)
                    del _PROGRAMS[next(iter(_PROGRAMS))]
            path = emitter.build(emitter.source(program), what, key)
        self.kernel = emitter.Kernel(path, sys.dtype, self.device, **options)
        self.fields = [(x.shape[1:], x.dtype) for x in (*state[:STEPPED], ctrl)]

    def __call__(self, sys: System, state: State, ctrl: torch.Tensor) -> State:
        names = [f"state.{field}" for field in State._fields[:STEPPED]] + ["ctrl"]
        batch = ctrl.shape[0]
        for name, x, (shape, dtype) in zip(names, (*state[:STEPPED], ctrl), self.fields):
            if x.shape != (batch, *shape) or x.dtype != dtype or x.device != self.device:  # the code reads raw memory
                raise ValueError(f"{name} must be a {dtype} tensor of shape ({batch}, {', '.join(map(str, shape))}) "
                                 f"on {self.device} for this System's step kernel (ctrl has {batch} envs), got "
                                 f"{x.dtype} {tuple(x.shape)} on {x.device}")
        params = [sys.parameter(w) for w in self.where]
        for w, x in zip(self.where, params):
            if x.shape[0] != batch:
                raise ValueError(f"the per-env parameter {'.'.join(map(str, w))} has {x.shape[0]} envs, the state "
                                 f"{batch}")
        inputs = [x.contiguous() for x in (*state[:STEPPED], ctrl, *params)]
        outputs = [torch.empty_like(x) for x in inputs[:STEPPED]]
        self.kernel(batch, inputs, outputs, self.substeps)
        return State(*outputs, state.act)


def _graphs(sys: System, where: list[tuple], state: State, ctrl: torch.Tensor, params: list[torch.Tensor]):
    """The step's three row graphs, each taking the per-env parameters (lanes) as its last inputs; and where each
    pose row starts a step."""
    h, method = sys.substep_timestep, METHODS[sys.method]
    bodies = with_world(*(lanes.to_lanes(x, 1) for x in state[:4]))
    shapes = [x.shape for x in bodies]
    poses = join_poses(bodies)
    q = lanes.to_lanes(state.q).contiguous()
    leaves, spec = pytree.tree_flatten(method.step_terms(sys, bodies, q, h))
    per_env = [i for i, x in enumerate(leaves) if lanes.per_env(x)]

    def system(params):  # batch-first again for the System: lanes.param turns them back, row by row
        return sys.with_parameters(where, [lanes.from_lanes(x) for x in params])

    def terms(poses, q, *params):
        found = pytree.tree_flatten(method.step_terms(system(params), Bodies(*split_poses(poses, shapes)), q, h))[0]
        return tuple(found[i] for i in per_env)

    def substep(poses, ctrl, *terms_and_params):
        step_terms = list(leaves)  # the terms every env shares: constants of the graph
        for i, x in zip(per_env, terms_and_params[:len(per_env)]):
            step_terms[i] = x
        after = method.substep(system(terms_and_params[len(per_env):]), Bodies(*split_poses(poses, shapes)), ctrl,
                               pytree.tree_unflatten(step_terms, spec), h)
        return (join_poses(after),)

    def finish(*old_poses_and_params):
        old = State(*old_poses_and_params[:STEPPED], act=None)  # a System with activations has no kernel
        new = pipeline.finish_lanes(system(old_poses_and_params[STEPPED + 1:]), old,
                                    Bodies(*split_poses(old_poses_and_params[STEPPED], shapes)))
        return tuple(new)[:STEPPED]

    lanes_ctrl = lanes.to_lanes(ctrl).contiguous()
    params = [x.contiguous() for x in params]
    graphs = (rows.row_graph(terms, [poses, q, *params]),
              rows.row_graph(substep, [poses, lanes_ctrl, *(leaves[i] for i in per_env), *params]),
              rows.row_graph(finish, [*(x.contiguous() for x in pipeline.to_lanes_state(state)[:STEPPED]), poses,
                                      *params]))
    # where each pose row starts a step: a row of the state (input t, its lanes row), or the world body's
    carried = []
    n = sys.num_bodies
    for t, x in enumerate(bodies):
        for c in range(x.shape[0]):
            carried += [("input", t, c * n + b) for b in range(n)]
            carried.append(("value", 1.0 if (t == 1 and c == 0) else 0.0))  # the world: at rest, identity
    return graphs, carried


def _wire(program: Program, graphs, carried, count: int) -> Program:
    """The Program: inputs 0-6 the state, 7 the controls, 8.. the per-env parameters; outputs the next state."""
    terms_graph, substep_graph, finish_graph = graphs
    params = [lambda r, k=k: ("input", 8 + k, r) for k in range(count)]
    start = [program.input_row(*c[1:]) if c[0] == "input" else c[1] for c in carried]
    terms = program.add(terms_graph, [lambda r: ("value", start[r]), lambda r: ("input", 4, r)] + params)
    rows_now = program.loop(start)
    after = program.add(substep_graph, [lambda r: ("value", rows_now[r]), lambda r: ("input", 7, r)]
                        + [lambda r, k=k: ("value", terms[k][r]) for k in range(len(terms))] + params)
    program.end_loop(after[0])
    new = program.add(finish_graph, [lambda r, t=t: ("input", t, r) for t in range(7)]
                      + [lambda r: ("value", rows_now[r])] + params)
    for k, field in enumerate(new):
        program.store(k, field)
    return program
