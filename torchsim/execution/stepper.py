"""How a step runs: a ``Stepper`` holds one System's execution strategy and its compiled code.

    stepper = torchsim.Stepper(sys)      # the fastest measured strategy for sys on its device
    state = stepper(state, ctrl)         # the results of torchsim.step(sys, state, ctrl), to float rounding

``torchsim.step`` is what a step computes; a Stepper is how it is executed. The strategies (measured:
``docs/benchmarks.md``):

- ``eager``: the reference step itself.
- ``kernel``: the whole step as one generated kernel (``execution.kernel``): C++ on a CPU, built in seconds and
  called once per step; CUDA C on a GPU (compiled by NVRTC), one launch per step. Per-env parameters are its inputs.
- ``loop``: the whole step compiled by ``torch.compile`` as one graph, its substeps a ``while_loop``.
- ``calls``: the substep and the step's end compiled separately, called from a Python loop.

:data:`STRATEGIES` is the one place a strategy is chosen: for each method and device type, the strategies that
can run it, the fastest first. A step that autograd records (an input requires grad, grad mode on) runs as
``calls`` on the whole batch, whatever the strategy: its compiled functions have a backward. Steppers hold no
process-wide state: two Systems with different strategies step side by side. Under ``torch.compile`` (a caller's
function traced around a Stepper: an env step, a collector step), a ``kernel`` Stepper is one operator of the
graph (``execution.step_op``), and CUDA graphs capture its launch; the others trace the reference step.
"""

import threading
import warnings

import torch

from torchsim import pipeline
from torchsim.execution import step_op
from torchsim.execution.compiled import Compiled
from torchsim.execution.kernel.step import StepKernel
from torchsim.execution.kernel.rows import Unsupported
from torchsim.state import State
from torchsim.system import System

#: (method, device type) -> the strategies that can run it, the fastest measured first (``eager`` runs anything).
#: Spring on a CPU: the C++ kernel 2.0-2.5x MuJoCo C at 4096 envs where the compiled ``loop`` ran 0.4-0.6x, and
#: 2.6-10x the inductor row graph it retired (``docs/execution.md``). XPBD: compiled substeps called from Python
#: (its step compiled as one loop kept gcc busy for over 10 minutes without finishing); no kernel yet.
STRATEGIES = {
    ("spring", "cpu"): ("kernel", "loop"),
    ("spring", "cuda"): ("kernel", "loop"),
    ("xpbd", "cpu"): ("calls",),
    ("xpbd", "cuda"): ("calls",),
}
NAMES = ("eager", "kernel", "loop", "calls")


def strategies(sys: System) -> tuple[str, ...]:
    """The strategies that can run ``sys``, the fastest first, ending with ``eager``."""
    return STRATEGIES.get((sys.method, sys.device.type), ()) + ("eager",)


class Stepper:
    """``torchsim.step`` for one System, run by one strategy (``"auto"``: the first of :func:`strategies`).

    Args:
        sys: the model; ``stepper.sys``.
        strategy: ``"auto"`` or one of :func:`strategies` ``(sys)``; another raises ValueError naming those.
        part_size, threads: ``loop`` and ``calls`` on CPU: batches stepped in parts of at most ``part_size`` envs
            (0: whole) on ``threads`` threads (default ``torch.get_num_threads()``); ``kernel`` on CPU: the OpenMP
            threads that share a batch.
        inductor_options: extra options for inductor (e.g. ``{"cpp.simdlen": 256}`` for AVX2 code).
        backend: ``"inductor"`` (generated code: the speed), or another ``torch.compile`` backend (``"aot_eager"``)
            that runs ``loop``'s and ``calls``' graphs op by op without generating code, in seconds instead of
            minutes; for telling an engine error from a code generator's.
        kernel_options: options for the GPU kernel (``block``: envs per thread block, ``emit_cuda.Kernel``).

    Each strategy compiles on its first step (a kernel in seconds, kept on disk for later processes). If the step
    cannot be expressed that way (an op outside the kernel's contract, no C++ compiler, no NVRTC), the stepper
    falls back to the next strategy with one warning instead of failing.
    """

    def __init__(self, sys: System, strategy: str = "auto", *, part_size: int = 512, threads: int | None = None,
                 inductor_options: dict | None = None, backend: str = "inductor", kernel_options: dict | None = None,
                 _shared: dict | None = None):
        self.sys, self.requested = sys, strategy
        allowed = strategies(sys)
        self.strategy = allowed[0] if strategy == "auto" else strategy
        if self.strategy not in allowed:
            known = "" if strategy in NAMES else f"unknown strategy {strategy!r}; "
            raise ValueError(f"Stepper: {known}the {sys.method} method on {sys.device.type} runs as {allowed} "
                             f"(or 'auto'), not {strategy!r}")
        self.threads = torch.get_num_threads() if threads is None else threads
        self.kernel_options = dict(kernel_options or {})
        # compiled code and part settings, shared with the steppers ``for_system`` makes
        self._shared = {} if _shared is None else _shared
        self.compiled = Compiled(sys, self._shared, part_size, self.threads, inductor_options, backend)
        self._lock = threading.Lock()
        self._sys_tensors = [x for x in sys.leaves() if isinstance(x, torch.Tensor)]
        self._kernel_built = None  # (the System tensors' versions, the StepKernel built for them)
        self.per_env = sys.per_env_parameters()  # where its per-env parameters are: inputs of a traced step
        self.handle = step_op.register(self)

    def __repr__(self) -> str:
        backend = "" if self.compiled.backend == "inductor" else f", backend={self.compiled.backend!r}"
        return f"Stepper({self.sys.method}, {self.strategy!r}, {self.sys.device}, {self.sys.dtype}{backend})"

    @property
    def parts(self):
        """How ``loop`` and ``calls`` cut CPU batches (``execution.parts.Parts``)."""
        return self.compiled.parts(self.strategy)

    def for_system(self, sys: System) -> "Stepper":
        """A stepper like this one for ``sys`` (e.g. with per-env parameters): this one if ``sys`` is its System;
        compiled code that takes the System as an input is shared, and so is a step kernel built for the same shared
        values (its per-env parameters are inputs), and the parts (their threads, and which part sizes have
        compiled)."""
        if sys is self.sys:
            return self
        return Stepper(sys, self.requested, part_size=self.compiled.part_size, threads=self.threads,
                       inductor_options=self.compiled.inductor_options, backend=self.compiled.backend,
                       kernel_options=self.kernel_options, _shared=self._shared)

    def __call__(self, state: State, ctrl: torch.Tensor) -> State:
        sys = self.sys
        if torch.compiler.is_compiling():  # a caller's graph: the kernel as one node, else the reference step traced
            if self.strategy == "kernel" and not pipeline.records_grad(sys, state, ctrl):
                return step_op.step(self, state, ctrl)
            return pipeline.step(sys, state, ctrl)
        if self.strategy == "eager":
            return pipeline.step(sys, state, ctrl)
        pipeline.check(sys, "ctrl", ctrl, sys.nu, state.x_pos.shape[0])
        if pipeline.records_grad(sys, state, ctrl):
            return self.compiled.recording_step(state, ctrl)
        if self.strategy == "kernel":
            try:
                kernel = self._kernel()
            except Unsupported as err:  # raised while building, before anything is stepped
                self._fall_back(err)
                return self(state, ctrl)
            return kernel(sys, state, ctrl)
        return self.compiled.step(self.strategy, state, ctrl)

    @property
    def needs_building(self) -> bool:
        """Whether the next step builds (or loads) the kernel first."""
        return self.strategy == "kernel" and self._kernel_built is None

    def build(self) -> None:
        """Build or load the kernel now (else on the first step), falling back to the next strategy as a step does."""
        try:
            self._kernel()
        except Unsupported as err:
            self._fall_back(err)

    def _fall_back(self, err: Exception) -> None:
        """The step cannot run as this strategy: use the next one, with one warning."""
        allowed = strategies(self.sys)
        failed, self.strategy = self.strategy, allowed[allowed.index(self.strategy) + 1]
        warnings.warn(f"Stepper: the {self.sys.method} step cannot run as the {failed} strategy ({err}); using the "
                      f"{self.strategy} strategy instead", stacklevel=3)

    def _kernel(self) -> StepKernel:
        """The step kernel for the System's shared values, built on first use and again if one of its tensors was
        edited in place (checked by version counters: ~5 us). Steppers ``for_system`` made for other per-env
        values share it."""
        versions, kernel = self._kernel_built or ((), None)
        if kernel is None or versions != [x._version for x in self._sys_tensors]:
            with self._lock:
                shared = self._shared.get("kernel")
                if shared is not None and shared[0] == self._shared_values():
                    kernel = shared[1]
                else:
                    threads = {"threads": self.threads} if self.sys.device.type == "cpu" else {}
                    kernel = StepKernel(self.sys, **threads, **self.kernel_options)
                    # the System's tensors kept alive with the key, so that no other tensor takes their addresses
                    self._shared["kernel"] = (self._shared_values(), kernel, self._sys_tensors)
                self._kernel_built = ([x._version for x in self._sys_tensors], kernel)
        return kernel

    @property
    def num_kernels(self) -> int:
        """Step kernels built or loaded by this stepper (one serves every batch)."""
        return int(self._kernel_built is not None)

    def _shared_values(self) -> tuple:
        """The identity and version of the System's shared tensors (what a kernel bakes in), and its other values."""
        per_env = {id(self.sys.parameter(w)) for w in self.sys.per_env_parameters()}
        return tuple((x.data_ptr(), x._version, x.shape) if isinstance(x, torch.Tensor) and id(x) not in per_env
                     else (x.shape if isinstance(x, torch.Tensor) else repr(x)) for x in self.sys.leaves())
