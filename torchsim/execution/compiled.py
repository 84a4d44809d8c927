"""The ``loop`` and ``calls`` strategies: the reference step compiled by ``torch.compile``.

- ``loop``: the whole step as one graph; its substeps one ``while_loop`` in the generated code, so a step returns to
  Python once, not once per substep (the Python side of a compiled call cost about a quarter of a 512-env substep).
- ``calls``: the substep and the step's end compiled separately, called from a Python loop; also how any step that
  autograd records runs (in torch 2.13 ``while_loop``'s gradients with respect to tensors its body captures came
  out wrong).

On CPU both step batches in parts of ``part_size`` envs on ``threads`` threads (``execution.parts``).
"""

import functools
import inspect

import torch
from torch._higher_order_ops.while_loop import while_loop

from torchsim import pipeline
from torchsim.execution.parts import Parts
from torchsim.kinematics import Bodies
from torchsim.methods import METHODS
from torchsim.state import State
from torchsim.system import System

# isolated: other steppers' compiled entries for a function (other models, batch sizes) do not count against this
# one's recompile limit, which fullgraph=True makes a hard error. torch 2.13 has the option; 2.11 (the GPU machine's
# build) has not, and there every stepper shares the limit
_ISOLATED = {"isolate_recompiles": True} if "isolate_recompiles" in inspect.signature(torch.compile).parameters else {}


def repeat_in_while_loop(n: int, fn, bodies: Bodies) -> Bodies:
    """``fn`` applied ``n`` times to ``bodies`` as one ``while_loop`` (``pipeline.run_substeps``' ``repeat``)."""
    def body(i, *b):
        return i + 1, *fn(Bodies(*b))

    start = torch.zeros((), dtype=torch.int64, device=bodies.x_pos.device)
    return Bodies(*while_loop(lambda i, *b: i < n, body, (start, *bodies))[1:])


class Compiled:
    """One System's ``torch.compile``'d step functions, shared (through ``shared``) between the steppers
    ``Stepper.for_system`` makes; see ``torchsim.Stepper`` for the arguments."""

    def __init__(self, sys: System, shared: dict, part_size: int, threads: int, inductor_options: dict | None,
                 backend: str):
        self.sys, self.shared, self.part_size, self.threads = sys, shared, part_size, threads
        self.inductor_options, self.backend = dict(inductor_options or {}), backend

    def parts(self, strategy: str) -> Parts:
        """How ``strategy`` cuts CPU batches: parts on threads for ``loop`` and ``calls``, else whole batches."""
        threaded = strategy in ("loop", "calls") and self.sys.device.type == "cpu"
        size, workers = (self.part_size, self.threads) if threaded else (0, 1)
        key = ("parts", size, workers)
        if key not in self.shared:
            self.shared[key] = Parts(size, workers)
        return self.shared[key]

    def step(self, strategy: str, state: State, ctrl: torch.Tensor) -> State:
        """One step by ``loop`` or ``calls``, in parts where the batch is cut."""
        parts = self.parts(strategy)
        threaded = parts.workers > 1
        if strategy == "loop":
            run = self._compile("loop", functools.partial(pipeline.run_substeps, repeat=repeat_in_while_loop),
                                threaded)
        else:
            method = METHODS[self.sys.method]
            run = functools.partial(pipeline.run_substeps, substep=self._compile(method.name, method.substep, threaded),
                                    finish_step=self._compile("finish", pipeline.finish, threaded))
        sizes = parts.sizes(state)
        if len(sizes) > 1:
            return parts.step(run, self.sys, state, ctrl, sizes)
        return run(self.sys, state, ctrl)

    def recording_step(self, state: State, ctrl: torch.Tensor) -> State:
        """A step autograd records: the ``calls`` strategy's compiled substep and step end, on the whole batch,
        from a Python loop. A step kernel has no backward, and the ``loop`` strategy's ``while_loop`` gave wrong
        gradients in torch 2.13; compiled functions do (AOTAutograd compiles a forward that saves what the backward
        needs, and the backward): equal to the reference step's to rounding (tests/test_compile.py;
        ``studies/grad_horizon.py compiled``), compiled once per model on the first recording step."""
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
        options = self._options(threaded)
        key = (name, self.backend, tuple(sorted(options.items())))
        if key not in self.shared:
            how = dict(options=options) if self.backend == "inductor" else dict(backend=self.backend)
            self.shared[key] = torch.compile(fn, fullgraph=True, dynamic=False, **_ISOLATED, **how)
        return self.shared[key]
