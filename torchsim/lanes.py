"""The engine's internal layout: components first, entities next, batch last ("lanes").

Public tensors (``State``, ``q``, ``ctrl``, ``System`` parameters) are batch-first with components last:
``(B, *E, *C)``, e.g. body positions ``(B, N, 3)``. Inside ``step`` every tensor is ``(*C, *E, B)``, e.g.
``(3, N, B)``: each elementwise op then runs over contiguous rows of ``B`` envs, which compiled code spreads over
SIMD lanes, where the batch-first layout left only the 3 or 4 components of a vector to vectorise over
(measured in commit 9b46b41, its ``docs/benchmarks.md``). A scalar field ``(*E, B)`` broadcasts against vectors ``(3, *E, B)`` and
matrices ``(3, 3, *E, B)`` as it is, and gathers over bodies or joints (axis ``-2`` for one entity axis) move whole
rows. ``step`` converts the state once on entry and once on exit; model constants are views with a batch axis of 1.
"""

import torch


def to_lanes(x: torch.Tensor, comps: int = 0) -> torch.Tensor:
    """``(B, *E, *C) -> (*C, *E, B)`` for ``comps`` component axes (a view)."""
    x = x.movedim(0, -1)
    return x.movedim(tuple(range(x.ndim - 1 - comps, x.ndim - 1)), tuple(range(comps))) if comps else x


def from_lanes(x: torch.Tensor, comps: int = 0) -> torch.Tensor:
    """``(*C, *E, B) -> (B, *E, *C)``, the inverse of :func:`to_lanes` (a view)."""
    x = x.movedim(-1, 0)
    return x.movedim(tuple(range(1, 1 + comps)), tuple(range(x.ndim - comps, x.ndim)))


def param(x: torch.Tensor, entities: int, comps: int = 0) -> torch.Tensor:
    """A ``System`` field ``(*E, *C)``, or batched per env ``(B, *E, *C)``, as ``(*C, *E, 1)`` or ``(*C, *E, B)``.

    ``entities`` and ``comps`` count the field's axes without the batch, so whether it is batched is read from its
    rank (static at trace time).
    """
    if x.ndim > entities + comps:
        return to_lanes(x, comps)
    x = x.unsqueeze(-1)  # the usual case, an unbatched field: one view op, which eager steps pay every substep
    return x.movedim(tuple(range(entities, entities + comps)), tuple(range(comps))) if comps else x


def components_last(fn, out_comps: int = 1):
    """``fn``, a ``torchsim.spatial`` function, for batch-first tensors with one component axis last (as ``State``'s
    fields and the envs hold them), broadcasting as batch-first tensors do: every tensor argument's last axis moves
    to the front, and the result's ``out_comps`` leading axes (2 for a matrix) move to the end."""

    def wrapped(*args):
        rank = max(a.ndim for a in args if isinstance(a, torch.Tensor))
        moved = [a.view((1,) * (rank - a.ndim) + a.shape).movedim(-1, 0) if isinstance(a, torch.Tensor) else a
                 for a in args]
        out = fn(*moved)
        return out.movedim(tuple(range(out_comps)), tuple(range(out.ndim - out_comps, out.ndim)))

    return wrapped


def per_env(x: torch.Tensor | None) -> bool:
    """Whether lanes tensor ``x`` holds one value per env (its last axis the batch, of more than one env); the
    others hold one value for all envs (last axis 1)."""
    return x is not None and x.shape[-1] > 1
