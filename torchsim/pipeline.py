"""``init`` and ``step``: the physics pipeline, the reference for every way of running it
(``torchsim.execution``).

The public state is batch-first (``State``); the substeps run in the lanes layout (``torchsim.lanes``): ``step``
converts the bodies on entry and ``finish`` converts them back.
"""

import warnings

import torch

from torchsim import activation, lanes
from torchsim.kinematics import Bodies, dof_window, forward, joint_frames, read_q, with_world
from torchsim.methods import METHODS
from torchsim.state import State
from torchsim.system import System


def check(sys: System, name: str, x: torch.Tensor, width: int, batch: int | None = None) -> None:
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    expected = f"({'B' if batch is None else batch}, {width})"
    if x.ndim != 2 or x.shape[1] != width or (batch is not None and x.shape[0] != batch):
        raise ValueError(f"{name} must have shape {expected}, got {tuple(x.shape)}")
    if x.dtype != sys.dtype:
        raise ValueError(f"{name} must have dtype {sys.dtype} (the System's), got {x.dtype}; use sys.to(dtype=...)")
    if x.device != sys.device:
        raise ValueError(f"{name} is on {x.device} but the System is on {sys.device}; use sys.to(device=...)")


def init(sys: System, q: torch.Tensor, qd: torch.Tensor, act: torch.Tensor | None = None) -> State:
    """State for generalized coordinates ``q (B, nq)`` and velocities ``qd (B, nv)`` (MuJoCo's qpos/qvel layout)
    and activations ``act (B, na)`` (default: zero, MuJoCo's reset value)."""
    check(sys, "q", q, sys.nq)
    check(sys, "qd", qd, sys.nv, q.shape[0])
    if act is None:
        act = q.new_zeros(q.shape[0], sys.na)
    check(sys, "act", act, sys.na, q.shape[0])
    bodies = with_world(*forward(sys, q, qd))
    q, qd = read_q(sys, bodies, joint_frames(sys, bodies), dof_window(sys, lanes.to_lanes(q)))
    n = sys.num_bodies
    return to_public(State(*(x[..., :n, :] for x in bodies), q, qd,
                           torch.zeros(q.shape[-1], dtype=torch.bool, device=q.device), lanes.to_lanes(act)))


def to_lanes_state(state: State) -> State:
    """A public (batch-first) State in the lanes layout: poses ``(3|4, N, B)``, ``q (nq, B)``, ``qd (nv, B)``,
    ``diverged (B,)``, ``act (na, B)`` (views)."""
    return State(*(lanes.to_lanes(x, 1) for x in state[:4]), lanes.to_lanes(state.q), lanes.to_lanes(state.qd),
                 state.diverged, lanes.to_lanes(state.act))


def to_public(state: State) -> State:
    """A lanes State batch-first, the inverse of :func:`to_lanes_state`.

    Contiguous, so that ``init``'s and ``step``'s results have the same strides (a batch of 1 included): a compiled
    graph guards on strides and would otherwise compile a second time on the first step's output.
    """
    return State(*(lanes.from_lanes(x, 1).contiguous() for x in state[:4]), lanes.from_lanes(state.q).contiguous(),
                 lanes.from_lanes(state.qd).contiguous(), state.diverged, lanes.from_lanes(state.act).contiguous())


def step(sys: System, state: State, ctrl: torch.Tensor) -> State:
    """Advance every env by ``sys.timestep`` under controls ``ctrl (B, nu)``: ``sys.substeps`` substeps of the
    System's method, then ``q, qd`` read back and divergence contained.

    The reference step: plain torch ops, runnable eagerly with autograd. ``torchsim.Stepper`` runs the same step
    compiled (same results); traced by ``torch.compile`` as it is, it warns once that the Stepper is faster."""
    check(sys, "ctrl", ctrl, sys.nu, state.x_pos.shape[0])
    if torch.compiler.is_compiling():  # the caller compiles a function around the step (e.g. torch.compile(step))
        warnings.warn(SLOW_COMPILE_WARNING, stacklevel=2)
    return run_substeps(sys, state, ctrl)


SLOW_COMPILE_WARNING = (
    "torchsim.step is being traced by torch.compile: the step then compiles as loop nests over (components, batch), "
    "its substeps unrolled (minutes to build), several times slower on CPU than the engine's own compiled step. For "
    "that, build a torchsim.Stepper(sys) once and call it (envs: stepper='auto'): where its strategy is 'kernel', "
    "a function torch.compile traces around it holds the step as one operator (torchsim.execution.step_op).")
# dynamo runs warnings.warn after the graph instead of breaking the graph on it (fullgraph=True would fail)
torch._dynamo.config.reorderable_logging_functions.add(warnings.warn)


def run_substeps(sys: System, state: State, ctrl: torch.Tensor, substep=None, finish_step=None,
                 repeat=None) -> State:
    """``step`` without its input check, the outline every way of running a step follows: the method's step terms
    from the poses at the step's start, ``sys.substeps`` substeps, then ``finish_step`` (default :func:`finish`).
    With activation dynamics the activations at the step's start drive their actuators through the substeps and
    advance once at its end, as MuJoCo's Euler step integrates ``act`` (``torchsim.activation``).

    ``substep``: the method's substep function (default: the eager one), e.g. compiled; ``repeat(n, fn, bodies)``:
    how the substeps are repeated (default: a Python loop; ``torchsim.execution.compiled`` passes a ``while_loop``).
    """
    method = METHODS[sys.method]
    substep, finish_step, repeat = substep or method.substep, finish_step or finish, repeat or repeat_in_python
    h = sys.substep_timestep
    bodies, ctrl = to_lanes(state, ctrl)
    if sys.na:  # static: MuJoCo's activations drive their actuators over the step and advance at its end
        ctrl, act_next = activation.drive(sys, ctrl, lanes.to_lanes(state.act))
    terms = method.step_terms(sys, bodies, lanes.to_lanes(state.q), h)
    bodies = repeat(sys.substeps, lambda b: substep(sys, b, ctrl, terms, h), bodies)
    new = finish_step(sys, state, bodies)
    if sys.na:  # a diverged env keeps its activations with the rest of its last good state
        new = new._replace(act=torch.where(new.diverged[:, None], state.act, lanes.from_lanes(act_next)))
    return new


def repeat_in_python(n: int, fn, bodies: Bodies) -> Bodies:
    """``fn`` applied ``n`` times to ``bodies``."""
    for _ in range(n):
        bodies = fn(bodies)
    return bodies


def to_lanes(state: State, ctrl: torch.Tensor) -> tuple[Bodies, torch.Tensor]:
    """The state's bodies (with the world body) and ``ctrl`` in the lanes layout."""
    return with_world(*(lanes.to_lanes(x, 1) for x in state[:4])), lanes.to_lanes(ctrl).contiguous()


def records_grad(sys: System, state: State, ctrl: torch.Tensor) -> bool:
    """Whether autograd would record a step: grad mode on and some input requiring grad."""
    return torch.is_grad_enabled() and (
        sys.requires_grad or ctrl.requires_grad or any(x.requires_grad for x in (*state[:4], state.act)))


def finish(sys: System, old: State, bodies: Bodies) -> State:
    """The state after a step's substeps from lanes ``bodies``: :func:`finish_lanes`, batch-first."""
    return to_public(finish_lanes(sys, to_lanes_state(old), bodies))


def finish_lanes(sys: System, old: State, bodies: Bodies) -> State:
    """The lanes State (:func:`to_lanes_state`) after a step from ``old``'s: the moving bodies of ``bodies``,
    ``q, qd`` read back from them, divergence contained; ``old``'s activations (:func:`run_substeps` advances
    them)."""
    q, qd = read_q(sys, bodies, joint_frames(sys, bodies), dof_window(sys, old.q))
    n = sys.num_bodies
    return contain_divergence(sys, old, State(*(x[..., :n, :] for x in bodies), q, qd, old.diverged, old.act))


def contain_divergence(sys: System, old: State, new: State) -> State:
    """Flag envs whose new state (lanes, :func:`to_lanes_state`) is non-finite or out of bounds, and keep them at
    their last good state.

    Envs never mix inside a step, so a diverged env cannot disturb the others; freezing it keeps its numbers
    finite until the caller re-initialises it (e.g. a partial reset).
    """
    finite = torch.stack([torch.isfinite(t).flatten(0, -2).all(0) for t in new[:6]]).all(0)
    in_bounds = (new.x_pos.abs().amax((0, 1)) < sys.max_distance) & (
        torch.maximum(new.xd_vel.abs().amax((0, 1)), new.xd_ang.abs().amax((0, 1))) < sys.max_speed)
    diverged = old.diverged | ~(finite & in_bounds)
    return State(*(torch.where(diverged, o, n) for o, n in zip(old[:6], new[:6])), diverged, new.act)
