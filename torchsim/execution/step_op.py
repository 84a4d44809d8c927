"""The ``kernel`` strategy as a torch operator, ``torch.ops.torchsim.step``, for code that ``torch.compile`` traces.

A function that steps a :class:`~torchsim.execution.Stepper` under ``torch.compile`` (an env step with its
observation, reward and resets; a collector step with its policy) holds the whole physics step as this one node:
dynamo does not trace the reference step (minutes of inductor's compile for the Ant, and thousands of small
launches on a GPU), and CUDA graphs (``mode="reduce-overhead"``) capture the kernel's one launch with the ops
around it, so a captured collector step runs without the host.

The operator takes the state's fields, the controls and the System's per-env parameters (everything the kernel
reads: a graph replay then reads them from the graph's own inputs) and returns the next state's fields; which
Stepper runs it is a constant of the graph (a handle registered here). Its fake version shapes the outputs as the
state; the real one runs the Stepper outside tracing, which builds or loads the kernel on first use, checks the
inputs, and falls back to another strategy as the Stepper does.
"""

import concurrent.futures
import itertools
import weakref

import torch

from torchsim.state import State

_STEPPERS: "weakref.WeakValueDictionary[int, object]" = weakref.WeakValueDictionary()
_HANDLES = itertools.count()


def register(stepper) -> int:
    """A handle by which the operator finds ``stepper`` (held weakly: a graph outliving it raises)."""
    handle = next(_HANDLES)
    _STEPPERS[handle] = stepper
    return handle


@torch.library.custom_op("torchsim::step", mutates_args=())
def _step(handle: int, tensors: list[torch.Tensor]) -> list[torch.Tensor]:
    stepper = _STEPPERS.get(handle)
    if stepper is None:
        raise RuntimeError(f"torchsim::step: the Stepper this graph was traced with (handle {handle}) is gone")
    n = len(State._fields)
    state, ctrl, params = State(*tensors[:n]), tensors[n], tensors[n + 1:]
    if any(p is not stepper.sys.parameter(w) for w, p in zip(stepper.per_env, params)):  # a compiled graph's copies
        stepper = stepper.for_system(stepper.sys.with_parameters(stepper.per_env, params))
    if stepper.needs_building:
        # built on a thread of its own: this thread runs an operator's implementation, with the autograd dispatch
        # keys excluded, and the kernel's row recording (rows.row_graph) then meets ops it does not know
        with concurrent.futures.ThreadPoolExecutor(1) as pool:
            pool.submit(stepper.build).result()
    inputs = {id(x) for x in tensors}  # an operator's outputs may not be its inputs (a fallback may pass one on)
    return [x.clone() if id(x) in inputs else x for x in stepper(state, ctrl)]


@_step.register_fake
def _(handle: int, tensors: list[torch.Tensor]) -> list[torch.Tensor]:
    return [torch.empty_like(x) for x in tensors[:len(State._fields)]]


def step(stepper, state: State, ctrl: torch.Tensor) -> State:
    """``stepper(state, ctrl)`` as one ``torch.ops.torchsim.step`` node of a traced graph."""
    params = [stepper.sys.parameter(w) for w in stepper.per_env]
    return State(*torch.ops.torchsim.step(stepper.handle, [*state, ctrl, *params]))
