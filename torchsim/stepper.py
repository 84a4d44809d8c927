"""How a step runs: a ``Stepper`` holds one System's execution strategy and its compiled code.

    stepper = torchsim.Stepper(sys)      # the fastest measured strategy for sys on its device
    state = stepper(state, ctrl)         # the results of torchsim.step(sys, state, ctrl), to float rounding

``torchsim.step`` is what a step computes; a Stepper is how it is executed. Strategies (their measured reasons:
``docs/physics.md``, "How a step runs"):

- ``eager``: the reference step itself.
- ``kernel`` (spring, CPU with AVX2 or AVX-512): the whole step as one generated C++ function
  (``torchsim.step_kernel``): built in seconds, one call per step at any batch size; per-env parameters are its
  inputs.
- ``rows`` (spring, CPU, parameters shared by every env): the substep as a row graph (``torchsim.rows``: every
  small axis unrolled, the model's constants folded in), which inductor compiles into one loop over the batch on
  every intra-op thread; Python calls it ``sys.substeps`` times between the compiled step terms and step end.
  One graph serves every batch of more than one env; a batch of one compiles its own.
- ``loop``: the whole step compiled by ``torch.compile`` as one graph, its substeps a ``while_loop``.
- ``calls``: the substep and the step's end compiled separately, called from a Python loop.

``loop`` and ``calls`` step CPU batches in parts of ``part_size`` envs on ``threads`` threads (``torchsim.parts``).
A step that autograd records (an input requires grad, grad mode on) runs as ``calls`` on the whole batch, whatever
the strategy: its compiled functions have a backward.
Steppers hold no process-wide state: two Systems with different strategies step side by side.
"""

import functools
import inspect
import math
import threading
import warnings

import torch
import torch.utils._pytree as pytree

from torchsim import lanes, pipeline, progress, row_cache, rows
from torchsim.kinematics import Bodies
from torchsim.methods import METHODS
from torchsim.parts import Parts
from torchsim.state import State
from torchsim.step_kernel import StepKernel, join_poses, split_poses
from torchsim.system import System

STRATEGIES = ("eager", "kernel", "rows", "loop", "calls")
# isolated: other steppers' compiled entries for a function (other models, batch sizes) do not count against this
# one's recompile limit, which fullgraph=True makes a hard error. torch 2.13 has the option; 2.11 (the GPU machine's
# build) has not, and there every stepper shares the limit
_ISOLATED = {"isolate_recompiles": True} if "isolate_recompiles" in inspect.signature(torch.compile).parameters else {}


def choose_strategy(sys: System) -> str:
    """The fastest measured strategy for ``sys`` on its device: the first of its method's ``strategies`` that
    applies (``kernel`` and ``rows`` only on CPU, ``rows`` only with parameters shared by every env), else the next
    one."""
    for strategy in METHODS[sys.method].strategies:
        if _unsupported(sys, strategy) is None:
            return strategy
    return "eager"


def _unsupported(sys: System, strategy: str) -> str | None:
    """Why ``strategy`` cannot run ``sys`` (None: it can)."""
    if strategy not in STRATEGIES:
        return f"unknown strategy {strategy!r}; expected 'auto' or one of {STRATEGIES}"
    if strategy != "eager" and strategy not in METHODS[sys.method].strategies:
        return f"the {sys.method} method supports {('eager',) + METHODS[sys.method].strategies}, not {strategy!r}"
    if strategy in ("kernel", "rows") and sys.device.type != "cpu":
        return f"the {strategy} strategy runs on CPU only"
    if strategy == "rows" and sys.batched:
        return "the rows strategy bakes the System's parameters in, so it needs parameters shared by every env"
    return None


class Stepper:
    """``torchsim.step`` for one System, run by one strategy (``"auto"``: :func:`choose_strategy`).

    Args:
        sys: the model; ``stepper.sys``.
        strategy: ``"auto"`` or one of ``STRATEGIES``; a strategy that cannot run ``sys`` raises ValueError.
        part_size, threads: ``loop`` and ``calls`` on CPU: batches stepped in parts of at most ``part_size`` envs
            (0: whole) on ``threads`` threads (default ``torch.get_num_threads()``).
        inductor_options: extra options for inductor (e.g. ``{"cpp.simdlen": 256}`` for AVX2 code).
        backend: ``"inductor"`` (generated C++: the speed), or another ``torch.compile`` backend (``"aot_eager"``)
            that runs the same graphs op by op without generating code: the strategy's graphs, substep loop and
            parts at eager speed, in seconds instead of minutes; for telling an engine error from a code
            generator's, and for checking every model's strategies.

    Each strategy compiles on its first step: a ``kernel`` stepper then builds its C++ step (seconds), a ``rows``
    stepper its row graph (minutes); both are kept on disk for later processes (``torchsim.row_cache``). If the
    step cannot be expressed that way (or the CPU lacks AVX2), the stepper falls back to the method's next strategy
    with one warning instead of failing.
    """

    def __init__(self, sys: System, strategy: str = "auto", *, part_size: int = 512, threads: int | None = None,
                 inductor_options: dict | None = None, backend: str = "inductor", _shared: dict | None = None):
        self.sys, self.requested = sys, strategy
        self.strategy = choose_strategy(sys) if strategy == "auto" else strategy
        reason = _unsupported(sys, self.strategy)
        if reason is not None:
            raise ValueError(f"Stepper: {reason}")
        self.part_size = part_size
        self.threads = torch.get_num_threads() if threads is None else threads
        self.inductor_options = dict(inductor_options or {})
        self.backend = backend
        # compiled functions and part settings, shared with the steppers ``for_system`` makes
        self._shared = {} if _shared is None else _shared
        self._row_graphs: dict[tuple, object] = {}
        self._row_lock = threading.Lock()
        self._sys_tensors = [x for x in sys.leaves() if isinstance(x, torch.Tensor)]
        self._kernel_built = None  # (the System tensors' versions, the StepKernel built for them)
        self.parts = self._parts()

    def __repr__(self) -> str:
        backend = "" if self.backend == "inductor" else f", backend={self.backend!r}"
        return f"Stepper({self.sys.method}, {self.strategy!r}, {self.sys.device}, {self.sys.dtype}{backend})"

    @property
    def num_row_graphs(self) -> int:
        """Row graphs and step kernels built so far (one serves every batch of more than one env; a batch of one
        builds its own row graph, not its own kernel)."""
        return len(self._row_graphs) + (self._kernel_built is not None)

    def for_system(self, sys: System) -> "Stepper":
        """A stepper like this one for ``sys`` (e.g. with per-env parameters): this one if ``sys`` is its System;
        compiled code that takes the System as an input is shared, and so is a step kernel built for the same shared
        values (its per-env parameters are inputs), and the parts (their threads, and which part sizes have
        compiled); a row graph, which bakes the System in, is not."""
        if sys is self.sys:
            return self
        return Stepper(sys, self.requested, part_size=self.part_size, threads=self.threads,
                       inductor_options=self.inductor_options, backend=self.backend, _shared=self._shared)

    def __call__(self, state: State, ctrl: torch.Tensor) -> State:
        sys = self.sys
        if self.strategy == "eager" or torch.compiler.is_compiling():
            return pipeline.step(sys, state, ctrl)
        pipeline.check(sys, "ctrl", ctrl, sys.nu, state.x_pos.shape[0])
        if pipeline.records_grad(sys, state, ctrl):
            return self._recording_step(state, ctrl)
        if self.strategy in ("kernel", "rows"):
            try:
                return self._kernel(state, ctrl) if self.strategy == "kernel" else self._rows_step(state, ctrl)
            except rows.Unsupported as err:  # raised while building, before anything is stepped
                self._fall_back(err)
                return self(state, ctrl)
        run = self._compiled_loop() if self.strategy == "loop" else self._compiled_calls()
        sizes = self.parts.sizes(state)
        if len(sizes) > 1:
            return self.parts.step(run, sys, state, ctrl, sizes)
        return run(sys, state, ctrl)

    # -- loop and calls
    def _parts(self) -> Parts:
        """How this strategy cuts CPU batches: parts on threads for ``loop`` and ``calls``, else whole batches."""
        threaded = self.strategy in ("loop", "calls") and self.sys.device.type == "cpu"
        size, workers = (self.part_size, self.threads) if threaded else (0, 1)
        key = ("parts", size, workers)
        if key not in self._shared:
            self._shared[key] = Parts(size, workers)
        return self._shared[key]

    def _options(self, threaded: bool) -> dict:
        """Inductor's options: its C++ wrapper (a substep is one kernel with ~120 buffers, and driving those from
        Python cost about as much as the kernel below batch ~100); single-threaded kernels where parts run on
        threads (their OpenMP loops do not scale)."""
        # CUDA keeps the Python wrapper: torch 2.11's C++ wrapper for CUDA graphs fails to build the step
        # (an inductor error in its buffer reuse), measured on an H100
        wrapper = {"cpp_wrapper": True} if self.sys.device.type == "cpu" else {}
        return wrapper | ({"cpp.threads": 1} if threaded else {}) | self.inductor_options

    def _compile(self, name: str, fn, threaded: bool = False):
        """``torch.compile(fn)`` once per name and options, shared with the steppers ``for_system`` made;
        ``threaded``: its kernels run inside parts on threads (else the whole batch on every intra-op thread)."""
        options = self._options(threaded and self.parts.workers > 1)
        key = (name, self.backend, tuple(sorted(options.items())))
        if key not in self._shared:
            how = dict(options=options) if self.backend == "inductor" else dict(backend=self.backend)
            self._shared[key] = torch.compile(fn, fullgraph=True, dynamic=False, **_ISOLATED, **how)
        return self._shared[key]

    def _compiled_loop(self):
        return self._compile("loop", pipeline.run_substeps, threaded=True)

    def _compiled_calls(self):
        method = METHODS[self.sys.method]
        return functools.partial(pipeline.run_substeps, substep=self._compile(method.name, method.substep, True),
                                 finish_step=self._compile("finish", pipeline.finish, True))

    def _recording_step(self, state: State, ctrl: torch.Tensor) -> State:
        """A step autograd records: the ``calls`` strategy's compiled substep and step end, on the whole batch,
        from a Python loop. The row graphs and the step kernel have no backward, and the ``loop`` strategy's
        ``while_loop`` gave wrong gradients in torch 2.13; compiled functions do (AOTAutograd compiles a forward
        that saves what the backward needs, and the backward): equal to the reference step's to rounding
        (tests/test_compile.py; ``scripts/grad_horizon.py compiled``), compiled once per model on the first
        recording step."""
        # Every float input made to require grad (constants as new leaves, whose gradients nobody reads): dynamo
        # guards on which inputs require grad, and a rollout mixes patterns (its detached start, then states that
        # depend on the controls), each of which would compile its own forward and backward (measured on APG's
        # unroll: 10 compilations of ~50 s instead of 4).
        state = State(*(x.detach().requires_grad_() if x.is_floating_point() and not x.requires_grad else x
                        for x in state))
        ctrl = ctrl if ctrl.requires_grad else ctrl.detach().requires_grad_()
        method = METHODS[self.sys.method]
        return pipeline.run_substeps(self.sys, state, ctrl, substep=self._compile(method.name, method.substep),
                                     finish_step=self._compile("finish", pipeline.finish))

    # -- kernel and rows
    def _fall_back(self, err: Exception) -> None:
        """The step cannot run as this strategy: use the method's next strategy, with one warning."""
        strategies = METHODS[self.sys.method].strategies
        later = strategies[strategies.index(self.strategy) + 1:]
        fallback = [s for s in later if _unsupported(self.sys, s) is None]
        failed, self.strategy = self.strategy, fallback[0] if fallback else "eager"
        warnings.warn(f"Stepper: the {self.sys.method} step cannot run as the {failed} strategy ({err}); using the "
                      f"{self.strategy} strategy instead", stacklevel=3)
        self.parts = self._parts()

    def _kernel(self, state: State, ctrl: torch.Tensor) -> State:
        """The step as one C++ function (``torchsim.step_kernel``), built on first use for the System's shared values
        and again if one of its tensors was edited in place (checked by version counters: ~5 us, where the row
        graphs' ``rows.system_key`` costs ~45 us, as much as a batch-1 step). Steppers ``for_system`` made for other
        per-env values share it."""
        versions, kernel = self._kernel_built or ((), None)
        if kernel is None or versions != [x._version for x in self._sys_tensors]:
            with self._row_lock:
                shared = self._shared.get("kernel")
                if shared is not None and shared[0] == self._shared_values():
                    kernel = shared[1]
                else:
                    kernel = StepKernel(self.sys, self.threads)
                    # the System's tensors kept alive with the key, so that no other tensor takes their addresses
                    self._shared["kernel"] = (self._shared_values(), kernel, self._sys_tensors)
                self._kernel_built = ([x._version for x in self._sys_tensors], kernel)
        return kernel(self.sys, state, ctrl)

    def _shared_values(self) -> tuple:
        """The identity and version of the System's shared tensors (what a kernel bakes in), and its other values."""
        per_env = {id(self.sys.parameter(w)) for w in self.sys.per_env_parameters()}
        return tuple((x.data_ptr(), x._version, x.shape) if isinstance(x, torch.Tensor) and id(x) not in per_env
                     else (x.shape if isinstance(x, torch.Tensor) else repr(x)) for x in self.sys.leaves())

    def _rows_step(self, state: State, ctrl: torch.Tensor) -> State:
        """The step with its substep a row graph that Python calls once per substep, between the compiled step terms
        and step end (dynamo, batch axis dynamic). The poses travel between substeps as one ``(rows, B)`` tensor,
        the graph's one output."""
        sys, h = self.sys, self.sys.substep_timestep
        method = METHODS[sys.method]
        bodies, ctrl = pipeline.to_lanes(state, ctrl)
        q = lanes.to_lanes(state.q)
        _batch_dynamic((), (*bodies, q))  # the step terms' only per-env inputs
        terms = self._compile("terms", _step_terms)(sys, bodies, q, h)
        inputs, spec = pytree.tree_flatten((ctrl, terms))
        shapes = [x.shape for x in bodies]
        # The controls and terms travel as two tensors, their per-env rows and their shared ones: a compiled call
        # costs ~0.5 us per tensor argument, and there are ~200.
        per_env_rows, shared_rows, layout, unpack = _pack(inputs)

        def substep_of_rows(poses, per_env_rows, shared_rows):
            ctrl, terms = pytree.tree_unflatten(unpack(per_env_rows, shared_rows), spec)
            return join_poses(method.substep(sys, Bodies(*split_poses(poses, shapes)), ctrl, terms, h))

        poses = join_poses(bodies)
        substep = self._row_graph(substep_of_rows, [poses, per_env_rows, shared_rows], layout)
        for _ in range(sys.substeps):
            poses = substep(poses, per_env_rows, shared_rows)
        bodies = Bodies(*split_poses(poses, shapes))
        _batch_dynamic(state, bodies)
        return self._compile("finish", pipeline.finish)(sys, state, bodies)

    def _row_graph(self, substep, args: list, layout: tuple):
        """``substep`` (a function of the tensors ``args``, which pack leaves of ``layout``) as a compiled row graph
        for inputs like ``args`` with any number of envs; built on first use for the System's values and these
        shapes (a tensor of the System edited in place builds a new one)."""
        sys = self.sys
        key = (rows.system_key(sys), layout, tuple((x.shape[:-1], lanes.per_env(x), x.dtype) for x in args))
        graph = self._row_graphs.get(key)
        if graph is None:
            with self._row_lock:  # steps on several threads: one builds it
                graph = self._row_graphs.get(key)
                if graph is None:
                    graph = self._row_graphs[key] = self._build_row_graph(substep, args, layout)
        return graph

    def _build_row_graph(self, substep, args: list, layout: tuple):
        sys = self.sys
        if self.backend != "inductor":  # the row graph itself, its ops run one by one
            graph = rows.row_graph(lambda *xs: (substep(*xs),), args)
            return lambda *inputs: graph(*inputs)[0]
        # a row graph's ops all fuse into one loop: no cap on the size of a fused kernel; its buffers in one pool
        options = {"cpp_wrapper": True, "max_fusion_size": 1 << 20, "memory_planning": True} | self.inductor_options
        batches = "any batch" if lanes.per_env(args[0]) else "batch 1"
        with progress.announce(f"the {sys.method} substep as a row graph ({sys.num_bodies} bodies, {batches}, "
                               f"{args[0].dtype})"):
            return rows.compile_row_graph(substep, args, options, row_cache.content_key(sys, args, options, layout))


def _step_terms(sys: System, bodies: Bodies, q: torch.Tensor, h: float):
    """The method's step terms, as one function to compile."""
    return METHODS[sys.method].step_terms(sys, bodies, q, h)


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


def _pack(leaves: list):
    """Lanes tensors (or None) as two: ``per_env_rows (R, B)`` and ``shared_rows (S, 1)``; also their ``layout``
    (each leaf's small axes and whether it is per env, or None) and ``unpack(per_env_rows, shared_rows)``, which
    gives the list back as views, its batch size read from ``per_env_rows``."""
    layout = tuple(None if x is None else (tuple(x.shape[:-1]), lanes.per_env(x)) for x in leaves)
    given = [x for x in leaves if x is not None]
    batch = max(x.shape[-1] for x in given)

    def stack(env: bool, width: int) -> torch.Tensor:
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

    return stack(True, batch), stack(False, 1), layout, unpack
