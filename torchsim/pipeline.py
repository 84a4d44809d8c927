"""``init`` and ``step``: the physics pipeline, one function per stage.

The public state is batch-first (``State``); the substeps run in the lanes layout (``torchsim.lanes``): ``step``
converts the bodies on entry and ``finish`` converts them back.
"""

import functools
import math
import threading
import warnings

import torch
import torch.utils._pytree as pytree
from torch._higher_order_ops.while_loop import while_loop

from torchsim import lanes, parts, progress, row_cache, rows
from torchsim.kinematics import Bodies, forward, joint_frames, read_q, with_world
from torchsim.methods import spring, xpbd
from torchsim.state import State
from torchsim.system import System


def _check(sys: System, name: str, x: torch.Tensor, width: int, batch: int | None = None) -> None:
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    expected = f"({'B' if batch is None else batch}, {width})"
    if x.ndim != 2 or x.shape[1] != width or (batch is not None and x.shape[0] != batch):
        raise ValueError(f"{name} must have shape {expected}, got {tuple(x.shape)}")
    if x.dtype != sys.dtype:
        raise ValueError(f"{name} must have dtype {sys.dtype} (the System's), got {x.dtype}; use sys.to(dtype=...)")
    if x.device != sys.device:
        raise ValueError(f"{name} is on {x.device} but the System is on {sys.device}; use sys.to(device=...)")


def init(sys: System, q: torch.Tensor, qd: torch.Tensor) -> State:
    """State for generalized coordinates ``q (B, nq)`` and velocities ``qd (B, nv)`` (MuJoCo's qpos/qvel layout)."""
    _check(sys, "q", q, sys.nq)
    _check(sys, "qd", qd, sys.nv, q.shape[0])
    bodies = with_world(*forward(sys, q, qd))
    q, qd = read_q(sys, bodies, joint_frames(sys, bodies))
    return State(*public_poses(sys, bodies), q, qd, torch.zeros(q.shape[0], dtype=torch.bool, device=q.device))


def public_poses(sys: System, bodies: Bodies) -> list[torch.Tensor]:
    """The moving bodies' poses and velocities, batch-first ``(B, N, 3|4)``, from lanes ``bodies``.

    Contiguous, so that ``init``'s and ``step``'s results have the same strides (a batch of 1 included): a compiled
    graph guards on strides and would otherwise compile a second time on the first step's output.
    """
    n = sys.num_bodies
    return [lanes.from_lanes(x[..., :n, :], 1).contiguous() for x in bodies]


def step(sys: System, state: State, ctrl: torch.Tensor) -> State:
    """Advance every env by ``sys.timestep`` under controls ``ctrl (B, nu)`` (``sys.substeps`` substeps).

    After ``compile_substeps()``, the step runs compiled: a spring step on CPU as a row graph (``torchsim.rows``)
    over the whole batch, other steps with a CPU batch as parts of a few hundred envs on worker threads
    (``torchsim.parts``); the results are the same."""
    _check(sys, "ctrl", ctrl, sys.nu, state.x_pos.shape[0])
    if torch.compiler.is_compiling():  # the caller compiles a function around the step (e.g. torch.compile(step))
        warnings.warn(SLOW_COMPILE_WARNING, stacklevel=2)
    run, compiled = _substeps, _STEP["compiled"]
    if compiled is not None:
        if _records_grad(sys, state, ctrl):
            _warn_eager_for_grad()
        elif "rows" in compiled and sys.method in ROWS and _rows_supported(sys) and not torch.compiler.is_compiling():
            return compiled["rows"](sys, state, ctrl)  # one part: the row graph's loop runs on every thread
        else:
            run = compiled["loop" if LOOPED[sys.method] else "calls"]
    sizes = parts.part_sizes(state)
    if len(sizes) > 1:
        return parts.step_in_parts(run, sys, state, ctrl, sizes)
    return run(sys, state, ctrl)


SLOW_COMPILE_WARNING = (
    "torchsim.step is being traced by torch.compile: the step then compiles as loop nests over (components, batch), "
    "several times slower on CPU than the engine's own compiled step. For that, call torchsim.compile_substeps() "
    "once and call torchsim.step (or the env's step) without torch.compile around it.")
# dynamo runs warnings.warn after the graph instead of breaking the graph on it (fullgraph=True would fail)
torch._dynamo.config.reorderable_logging_functions.add(warnings.warn)


def _substeps(sys: System, state: State, ctrl: torch.Tensor, calls: dict | None = None) -> State:
    """``step`` of one batch (or part of one) on the calling thread; ``calls``: the substep functions by method and
    ``"finish"`` (default: eager), e.g. compiled ones.

    Compiled as a whole, the substeps are one ``while_loop`` in the generated code, so a step returns to Python
    once, not once per substep (the Python side of a compiled call cost about a quarter of a 512-env substep).
    Where autograd records the step, they stay a Python loop: in torch 2.13 ``while_loop``'s gradients with respect
    to tensors its body captures came out wrong (``docs/benchmarks.md``, speed pass 6).
    """
    calls = calls or _EAGER_CALLS
    h = sys.timestep / sys.substeps
    bodies, ctrl = _to_lanes(state, ctrl)
    terms = STEP_TERMS[sys.method](sys, bodies, h)
    substep = calls[sys.method]
    if torch.compiler.is_compiling() and not _records_grad(sys, state, ctrl):
        def body(i, *b):
            return i + 1, *substep(sys, Bodies(*b), ctrl, terms, h)

        start = torch.zeros((), dtype=torch.int64, device=ctrl.device)
        bodies = Bodies(*while_loop(lambda i, *b: i < sys.substeps, body, (start, *bodies))[1:])
    else:
        for _ in range(sys.substeps):
            bodies = substep(sys, bodies, ctrl, terms, h)
    return calls["finish"](sys, state, bodies)


def _to_lanes(state: State, ctrl: torch.Tensor) -> tuple[Bodies, torch.Tensor]:
    return with_world(*(lanes.to_lanes(x, 1) for x in state[:4])), lanes.to_lanes(ctrl).contiguous()


def _row_substeps(options: dict, calls: dict, sys: System, state: State, ctrl: torch.Tensor) -> State:
    """``_substeps`` with the substep a row graph (``torchsim.rows``, compiled with inductor ``options``) that
    Python calls once per substep; ``calls``: the compiled step terms and step end. The poses travel between
    substeps as one ``(rows, B)`` tensor, the graph's one output."""
    h = sys.timestep / sys.substeps
    bodies, ctrl = _to_lanes(state, ctrl)
    _batch_dynamic((), bodies)  # the step terms' only per-env inputs
    inputs, spec = pytree.tree_flatten((ctrl, calls["terms"](sys, bodies, h)))
    shapes = [x.shape for x in bodies]
    # The controls and terms travel as two tensors, their per-env rows and their shared ones: a compiled call
    # costs ~0.5 us per tensor argument, and there are ~200 (measured: X us of a batch-128 substep).
    per_env_rows, shared_rows, layout, unpack = _pack(inputs)

    def substep_of_rows(poses, per_env_rows, shared_rows):
        ctrl, terms = pytree.tree_unflatten(unpack(per_env_rows, shared_rows), spec)
        return _join_poses(SUBSTEP[sys.method](sys, Bodies(*_split_poses(poses, shapes)), ctrl, terms, h))

    poses = _join_poses(bodies)
    substep = _row_graph(options, sys, substep_of_rows, [poses, per_env_rows, shared_rows], layout)
    for _ in range(sys.substeps):
        poses = substep(poses, per_env_rows, shared_rows)
    bodies = Bodies(*_split_poses(poses, shapes))
    _batch_dynamic(state, bodies)
    return calls["finish"](sys, state, bodies)


def _batch_dynamic(batch_first, lanes_last) -> None:
    """Mark the batch axis of a row-graph step's tensors (``batch_first``: public state, ``lanes_last``: lanes
    tensors) dynamic for dynamo, as the row graph's is: the step's terms and end then compile once for every batch
    of more than one env, so that an evaluation batch shares the training batch's compiled step."""
    for x in batch_first:
        if x.shape[0] > 1:
            torch._dynamo.maybe_mark_dynamic(x, 0)
    for x in lanes_last:
        if lanes.per_env(x):
            torch._dynamo.maybe_mark_dynamic(x, x.ndim - 1)


def _join_poses(bodies: Bodies) -> torch.Tensor:
    """The lanes tensors of ``bodies`` as the rows of one ``(rows, B)`` tensor; ``_split_poses`` undoes it."""
    return torch.cat([x.reshape(-1, x.shape[-1]) for x in bodies])


def _split_poses(poses: torch.Tensor, shapes: list) -> list[torch.Tensor]:
    return [x.view(*shape[:-1], poses.shape[-1])  # the batch size of poses: row graphs trace at another
            for x, shape in zip(poses.split([shape[:-1].numel() for shape in shapes]), shapes)]


def _pack(leaves: list):
    """Lanes tensors (or None) as two: ``per_env_rows (R, B)`` and ``shared_rows (S, 1)``; also their ``layout``
    (each leaf's small axes and whether it is per env, or None) and ``unpack(per_env_rows, shared_rows)``, which
    gives the list back as views, its batch size read from ``per_env_rows``."""
    layout = tuple(None if x is None else (tuple(x.shape[:-1]), lanes.per_env(x)) for x in leaves)
    given = [x for x in leaves if x is not None]
    batch = max(x.shape[-1] for x in given)

    def rows(env: bool, width: int) -> torch.Tensor:
        return torch.cat([given[0].new_zeros((0, width))] +
                         [x.reshape(-1, width) for x in given if lanes.per_env(x) == env])

    def unpack(per_env_rows: torch.Tensor, shared_rows: torch.Tensor) -> list:
        at, out = {True: 0, False: 0}, []
        for leaf in layout:
            if leaf is None:
                out.append(None)
                continue
            shape, env = leaf
            n = math.prod(shape)
            source = per_env_rows if env else shared_rows
            out.append(source[at[env]:at[env] + n].view(*shape, source.shape[-1]))
            at[env] += n
        return out

    return rows(True, batch), rows(False, 1), layout, unpack


def _records_grad(sys: System, state: State, ctrl: torch.Tensor) -> bool:
    """Whether autograd would record a step: grad mode on and some input requiring grad."""
    return torch.is_grad_enabled() and (
        sys.requires_grad or ctrl.requires_grad or any(x.requires_grad for x in state[:4]))


@functools.cache
def _warn_eager_for_grad() -> None:
    warnings.warn("torchsim.step: an input requires grad, so this step and later ones that record gradients run "
                  "eagerly, not compiled (the compiled substep loop does not give correct gradients in torch 2.13)",
                  stacklevel=3)


def finish(sys: System, old: State, bodies: Bodies) -> State:
    """The state after a step's substeps: ``q, qd`` read back from the bodies, divergence contained."""
    q, qd = read_q(sys, bodies, joint_frames(sys, bodies))
    return contain_divergence(sys, old, State(*public_poses(sys, bodies), q, qd, old.diverged))


def contain_divergence(sys: System, old: State, new: State) -> State:
    """Flag envs whose new state is non-finite or out of bounds, and keep them at their last good state.

    Envs never mix inside a step, so a diverged env cannot disturb the others; freezing it keeps its numbers
    finite until the caller re-initialises it (e.g. a partial reset).
    """
    finite = torch.stack([torch.isfinite(t).flatten(1).all(1) for t in new[:6]]).all(0)
    in_bounds = (new.x_pos.abs().amax((1, 2)) < sys.max_distance) & (
        torch.maximum(new.xd_vel.abs().amax((1, 2)), new.xd_ang.abs().amax((1, 2))) < sys.max_speed)
    diverged = old.diverged | ~(finite & in_bounds)
    fields = [torch.where(diverged.view((-1,) + (1,) * (o.ndim - 1)), o, n) for o, n in zip(old[:6], new[:6])]
    return State(*fields, diverged)


#: Each solution method's substep ``(sys, bodies, ctrl, terms, h) -> bodies``, and the function building the
#: ``terms`` its substeps share from the poses at the step's start (``(sys, bodies, h) -> terms``; in a compiled
#: step with per-substep calls it runs eagerly).
SUBSTEP = {"spring": spring.substep, "xpbd": xpbd.substep}
STEP_TERMS = {"spring": spring.step_terms, "xpbd": xpbd.step_terms}


def _step_terms(sys: System, bodies: Bodies, h: float):
    """``STEP_TERMS`` of ``sys``'s method, as one function to compile (the row-graph step does)."""
    return STEP_TERMS[sys.method](sys, bodies, h)


_EAGER_CALLS = SUBSTEP | {"finish": finish}
#: Methods whose compiled CPU substep is a row graph (``torchsim.rows``) under ``compile_substeps(rows=True)``: one
#: loop over the batch instead of ~140 loop nests (``docs/benchmarks.md``, speed pass 9). xpbd's substep is
#: larger; its row graph was not tried.
ROWS = {"spring"}
#: Compiled row-graph substeps by (System key, input shapes), each with the System it baked in (kept alive, see
#: ``rows.system_key``); the oldest is dropped beyond ``ROW_GRAPHS_KEPT``.
_ROW_GRAPHS: dict[tuple, tuple] = {}
ROW_GRAPHS_KEPT = 8
_ROW_LOCK = threading.Lock()


def _rows_supported(sys: System) -> bool:
    """Row graphs bake the System in: they serve CPU models whose parameters are shared by every env."""
    return sys.device.type == "cpu" and not sys.batched


def _row_graph(options: dict, sys: System, substep, args: list, layout: tuple):
    """``substep`` (of ``sys``'s method, as a function of the tensors ``args``, which pack leaves of ``layout``)
    as a compiled row graph for inputs like ``args`` with any number of envs; built on first use for this System's
    values and these shapes."""
    key = (rows.system_key(sys), layout, tuple((x.shape[:-1], lanes.per_env(x), x.dtype) for x in args))
    entry = _ROW_GRAPHS.get(key)
    if entry is None:
        with _ROW_LOCK:  # steps on several threads: one builds it
            entry = _ROW_GRAPHS.get(key)
            if entry is None:
                batches = "any batch" if lanes.per_env(args[0]) else "batch 1"
                with progress.announce(f"the {sys.method} substep as a row graph ({sys.num_bodies} bodies, "
                                       f"{batches}, {args[0].dtype})"):
                    graph = rows.compile_row_graph(
                        substep, args, options, row_cache.content_key(sys, args, options, layout))
                    entry = _ROW_GRAPHS[key] = (sys, graph)
                while len(_ROW_GRAPHS) > ROW_GRAPHS_KEPT:
                    del _ROW_GRAPHS[next(iter(_ROW_GRAPHS))]
    return entry[1]


#: Whether ``compile_substeps`` compiles a method's step as one graph with its substeps in a loop (True) or
#: compiles the substep and the step's end as calls from Python. xpbd's loop graph kept gcc busy for over 10
#: minutes without finishing (spring's builds in ~2.5), so xpbd keeps the calls (``docs/benchmarks.md``, pass 6).
LOOPED = {"spring": True, "xpbd": False}
#: The compiled steps ``compile_substeps`` switched on (None: eager steps), and every set compiled so far.
_STEP: dict[str, dict | None] = {"compiled": None}
_COMPILED_STEP: dict[tuple[bool, ...], dict] = {}


def compile_substeps(enabled: bool = True, dynamic: bool = False, vectorize: bool = True,
                     cpp_wrapper: bool = True, part_size: int = 512, workers: int | None = None,
                     rows: bool = True) -> None:
    """Make every later ``step`` run compiled (``torch.compile(fullgraph=True)``; ``enabled=False``: eager again).

    ``rows=True`` (default): on CPU, with static shapes, a spring step whose System has no per-env parameters
    runs its substep as a row graph (``torchsim.rows``: every small axis unrolled, the model's constants folded
    in, one loop over the whole batch on every intra-op thread), compiled by inductor directly; a Python loop calls
    it ``sys.substeps`` times between the compiled step terms and step end. A row graph belongs to one System's
    values: another System, or a tensor of it edited in place, builds and compiles a new one (about 2 minutes for
    the ant; the last ``ROW_GRAPHS_KEPT`` are kept). It serves every batch of more than one env, and the step terms
    and end are compiled with a dynamic batch size too; a batch of one env compiles its own. Other cases keep the
    paths below.

    For the methods in ``LOOPED`` (spring) the step compiles as one graph in which the substeps are a
    ``while_loop`` over one copy of the substep: it compiles in about 2.5 minutes on CPU (``substeps`` unrolled
    copies would take far longer) and runs without returning to Python between substeps. For the others (xpbd) the
    substep and the step's end (reading ``q, qd`` back, the divergence check) compile separately and a Python loop
    calls them. Each compiles on its first use (once per method, dtype and part size). The switch is
    process-wide. Steps that autograd records (an input requires grad, grad mode on) run eagerly, with a warning:
    the loop's gradients are not trusted (see ``_substeps``).

    ``part_size`` (default 512; 0: off) and ``workers`` (default ``torch.get_num_threads()``): on CPU a batch is
    stepped as ``ceil(B / part_size)`` parts of near-equal size, spread over ``workers`` threads
    (``torchsim.parts``; same results). Parts of a few hundred envs run faster per env than large batches, and
    threads are how the step uses more than one core: the kernels are compiled single-threaded when
    ``workers > 1``, since their OpenMP loops do not scale (``docs/benchmarks.md``, speed pass 5).

    ``dynamic=False`` (default) compiles static shapes: one graph per part size. Every batch that is a multiple of
    ``part_size`` uses parts of exactly that size, so they share one compilation; other sizes add one (or two)
    each, and dynamo falls back to eager code for a function after 8 (``torch._dynamo.config.recompile_limit``).
    ``dynamic=True`` serves every size with one graph, but its code ran 1.5-2x slower on CPU.

    ``vectorize=True`` (default) lets inductor emit SIMD code for CPUs: in the lanes layout its innermost axis is the
    batch, so the lanes run across envs. ``vectorize=False`` compiles scalar code (``cpp.simdlen=1``), for
    comparison (``docs/benchmarks.md``). GPUs ignore the option.

    ``cpp_wrapper=True`` (default) has inductor write the code that allocates buffers and calls the kernels in C++
    instead of Python: a substep is one kernel with ~120 buffers, and driving those from Python cost about as much
    as the kernel itself below batch ~100 (batch 64: ~2x faster substeps; batch 4096: unchanged; measured when
    each substep was a call from Python). It adds ~10-25 s to each compilation. It was measured on CPU only; no
    GPU was at hand to test it, or the compiled loop, on CUDA.
    """
    workers = torch.get_num_threads() if workers is None else workers
    parts.PARTS.set(part_size if enabled else 0, workers if enabled else 1)
    whole_options = {"cpp_wrapper": cpp_wrapper} | ({} if vectorize else {"cpp.simdlen": 1})
    options = whole_options | ({"cpp.threads": 1} if workers > 1 else {})
    key = (dynamic, vectorize, cpp_wrapper, workers > 1, rows)
    if enabled and key not in _COMPILED_STEP:  # torch.compile is lazy: each compiles on its first call
        compiled = functools.partial(torch.compile, fullgraph=True, dynamic=dynamic, options=options)
        calls = {name: compiled(fn) for name, fn in _EAGER_CALLS.items()}
        steps = {"loop": compiled(_substeps), "calls": functools.partial(_substeps, calls=calls)}
        if rows and not dynamic:  # the whole batch at once, its kernels on every intra-op thread
            whole = functools.partial(torch.compile, fullgraph=True, dynamic=False, options=whole_options)
            # a row graph's ops all fuse into one loop: no cap on the size of a fused kernel; its buffers in one pool
            graph_options = whole_options | {"max_fusion_size": 1 << 20, "memory_planning": True}
            steps["rows"] = functools.partial(_row_substeps, graph_options, {"terms": whole(_step_terms),
                                                                             "finish": whole(finish)})
        _COMPILED_STEP[key] = steps
    _STEP["compiled"] = _COMPILED_STEP[key] if enabled else None
