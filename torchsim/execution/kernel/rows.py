"""Row graphs: a lanes-layout function rewritten so that every op acts on one row of ``B`` envs.

In the lanes layout (``torchsim.lanes``) a tensor is ``(*S, B)``: a few small static axes ``S`` (components,
bodies, joints) in front of the batch. A row graph unrolls ``S``: each tensor becomes an array of ``(B,)`` rows, so
gathers, concatenations, index sums and views become bookkeeping at trace time, and the model's constants fold into
the arithmetic (a joint mode of 0 removes the terms it multiplies). What is left is a straight line of elementwise
ops on rows, which ``program`` lowers to its row-op contract and the emitters turn into one loop over the batch whose
intermediates stay in registers.

Tensors the traced function closes over (the System's shared values) are baked into the graph as constants; per-env
parameters enter as lanes inputs. The small axes are static; the batch size is not, so one graph serves a training
batch and a small evaluation batch alike.

The module runs past 400 lines because its two halves are one mechanism: the interpreter's rule for each aten op
on rows, and the tracing around it that turns a lanes function into a row graph.
"""

import math
import operator

import numpy as np
import torch
from torch._guards import TracingContext, tracing
from torch._subclasses.fake_tensor import FakeTensorMode
from torch.fx import GraphModule, Interpreter
from torch.fx.experimental.proxy_tensor import disable_proxy_modes_tracing, make_fx

from torchsim import spatial
from torchsim.lanes import per_env

aten = torch.ops.aten


class Unsupported(NotImplementedError):
    """The function uses an op (or an op on an axis) that row graphs cannot express."""


def _cell(value) -> np.ndarray:
    """A 0-d object array holding ``value`` (``np.array`` would try to iterate a tensor)."""
    out = np.empty((), dtype=object)
    out[()] = value
    return out


def _is_num(x) -> bool:
    return isinstance(x, (bool, int, float))


def _map(fn, *arrays) -> np.ndarray:
    """``fn`` over the broadcast elements of object arrays."""
    arrays = [a if isinstance(a, np.ndarray) else _cell(a) for a in arrays]
    shape = np.broadcast_shapes(*(a.shape for a in arrays))
    arrays = [np.broadcast_to(a, shape) for a in arrays]
    out = np.empty(shape, dtype=object)
    for idx in np.ndindex(shape):
        out[idx] = fn(*(a[idx] for a in arrays))
    return out


class Rows:
    """A lanes tensor ``(*S, B)`` as an object array of shape ``S`` whose elements are rows: ``(B,)`` or ``(1,)``
    tensors, or Python numbers where the value is a model constant."""

    def __init__(self, cells: np.ndarray):
        self.cells = cells


class Moved:
    """A lanes tensor permuted so that its batch axis is not last: ``x.permute(dims)`` of :class:`Rows` ``x``. Only
    another permute may use it, and once the batch axis is last again it is rows again: a per-env System parameter
    enters a row graph as a lanes input, turned batch-first for the System and back by ``lanes.param``."""

    def __init__(self, rows: Rows, dims: list[int]):
        self.rows, self.dims = rows, dims


# Element ops. Python numbers are constants: ops on them fold, and 0 and 1 simplify products and sums (the
# structural zeros of a model, e.g. a hinge's unused axes, drop out of the graph).
def _mul(a, b):
    if _is_num(a) and not _is_num(b):
        a, b = b, a
    if _is_num(b) and not _is_num(a):
        return 0.0 if b == 0 and not isinstance(b, bool) else a if b == 1 else -a if b == -1 else a * b
    return a * b


def _add(a, b, alpha=1):
    b = _mul(b, alpha) if alpha != 1 else b
    if _is_num(a) and a == 0:
        return b
    return a if _is_num(b) and b == 0 else a + b


def _sub(a, b, alpha=1):
    b = _mul(b, alpha) if alpha != 1 else b
    if _is_num(b) and b == 0:
        return a
    return -b if _is_num(a) and a == 0 else a - b


def _div(a, b):
    if _is_num(b) and b == 1:
        return a
    return 0.0 if _is_num(a) and a == 0 and not _is_num(b) else a / b


def _unary(on_number, on_row):
    return lambda a: on_number(a) if _is_num(a) else on_row(a)


def _where(cond, a, b):
    if _is_num(cond):
        return a if cond else b
    return a if _is_num(a) and _is_num(b) and a == b else torch.where(cond, a, b)


def _clamp(a, lo=None, hi=None):
    if _is_num(a):
        return min(max(a, -math.inf if lo is None else lo), math.inf if hi is None else hi)
    return torch.clamp(a, lo, hi)


def _binary(on_numbers, on_rows):
    """An op that needs rows on both sides: a number meeting a row is made a full row."""
    def op(a, b):
        if _is_num(a) and _is_num(b):
            return on_numbers(a, b)
        a = torch.full_like(b, a) if _is_num(a) else a
        return on_rows(a, b if not _is_num(b) else torch.full_like(a, b))
    return op


def _and(a, b):
    if _is_num(a) or _is_num(b):
        a, b = (a, b) if _is_num(a) else (b, a)
        return b if a else False
    return a & b


def _to(a, dtype):
    if _is_num(a):
        return float(a) if dtype.is_floating_point else bool(a) if dtype == torch.bool else int(a)
    return a.to(dtype)


ELEMENTWISE = {
    aten.mul.Tensor: _mul, aten.add.Tensor: _add, aten.sub.Tensor: _sub, aten.div.Tensor: _div,
    aten.rsub.Scalar: lambda a, b, alpha=1: _sub(b, a, alpha),
    aten.neg.default: _unary(operator.neg, torch.neg),
    aten.rsqrt.default: _unary(lambda a: 1 / math.sqrt(a), torch.rsqrt),
    aten.sqrt.default: _unary(math.sqrt, torch.sqrt),
    aten.reciprocal.default: _unary(lambda a: 1 / a, torch.reciprocal),
    aten.relu.default: _unary(lambda a: max(a, 0.0), torch.relu),
    aten.cos.default: _unary(math.cos, torch.cos),
    aten.sin.default: _unary(math.sin, torch.sin),
    aten.where.self: _where,
    aten.clamp.default: _clamp,
    aten.clamp_min.default: lambda a, lo: _clamp(a, lo),
    aten.minimum.default: _binary(min, torch.minimum),
    aten.maximum.default: _binary(max, torch.maximum),
    aten.atan2.default: _binary(math.atan2, torch.atan2),
    aten.gt.Scalar: operator.gt, aten.gt.Tensor: operator.gt,
    aten.ge.Scalar: operator.ge, aten.ge.Tensor: operator.ge,
    aten.lt.Scalar: operator.lt, aten.lt.Tensor: operator.lt,
    aten.le.Scalar: operator.le, aten.le.Tensor: operator.le,
    aten.ne.Scalar: operator.ne, aten.ne.Tensor: operator.ne,
    aten.bitwise_and.Tensor: _and,
    aten._to_copy.default: lambda a, dtype=None, **_: _to(a, dtype),
}


def _pointwise(op):
    """Any other pointwise aten op, per element: on numbers alone it folds, otherwise numbers in Tensor arguments
    become 0-d tensors (Scalar arguments keep them)."""
    takes_tensor = [isinstance(a.type, torch.TensorType) for a in op._schema.arguments]

    def fn(*xs, **kwargs):
        rows = [x for x in xs if isinstance(x, torch.Tensor)]
        dtype = rows[0].dtype if rows else torch.float64
        args = [torch.tensor(x, dtype=dtype) if _is_num(x) and tensor else x for x, tensor in zip(xs, takes_tensor)]
        if not rows:
            with disable_proxy_modes_tracing():
                return op(*args, **kwargs).item()
        return op(*args, **kwargs)
    return fn


class _RowInterpreter(Interpreter):
    """Runs an aten graph of lanes tensors on :class:`Rows`; ops on constants alone run as they are (folding)."""

    def cells(self, x) -> np.ndarray:
        if isinstance(x, Rows):
            return x.cells
        if x is None or _is_num(x):
            return _cell(x)
        if x.ndim == 0:
            return _cell(x.item())
        if x.shape[-1] == 1:  # a constant (*S, 1): numbers
            values = x[..., 0]
            return np.array(values.tolist(), dtype=object).reshape(values.shape) if values.ndim else _cell(
                values.item())
        # a constant with a batch axis (e.g. zeros made batch-sized for a stack): rows, or numbers where a row is
        # one value repeated, so that it folds like any other constant
        rows = x.reshape(-1, x.shape[-1]).unbind(0)
        with disable_proxy_modes_tracing():
            flat = x.reshape(-1, x.shape[-1])
            uniform = (flat == flat[:, :1]).all(1).tolist()
            firsts = flat[:, 0].tolist()
        out = np.empty(len(rows), dtype=object)
        out[:] = [first if same else row for row, same, first in zip(rows, uniform, firsts)]
        return out.reshape(x.shape[:-1])

    def run_node(self, node):
        if node.op != "call_function":
            return super().run_node(node)
        args, kwargs = self.fetch_args_kwargs_from_env(node)
        if node.target is operator.getitem:
            return args[0][args[1]]
        flat = [y for x in (*args, *kwargs.values()) for y in (x if isinstance(x, (list, tuple)) else [x])]
        if any(isinstance(x, Moved) for x in flat) and node.target is not aten.permute.default:
            raise Unsupported(f"row graphs keep the batch axis last ({node.target} on a batch-first tensor)")
        if not any(isinstance(x, (Rows, Moved)) for x in flat):
            with disable_proxy_modes_tracing():
                return node.target(*args, **kwargs)
        if node.target in ELEMENTWISE or torch.Tag.pointwise in node.target.tags:
            fn = ELEMENTWISE.get(node.target) or _pointwise(node.target)
            tensors = [self.cells(a) for a in args]
            return Rows(_map(lambda *xs: fn(*xs, **kwargs), *tensors))
        handler = getattr(self, "_op_" + node.target.__name__.replace(".", "_"), None)
        if handler is None:
            raise Unsupported(f"row graphs do not support {node.target}")
        return handler(tuple(node.meta["val"].shape) if isinstance(node.meta.get("val"), torch.Tensor) else None,
                       *args, **kwargs)

    def _axis(self, cells: np.ndarray, dim: int, extra: int = 0) -> int:
        """The small axis that tensor dim ``dim`` names (rank ``cells.ndim + 1``, plus ``extra`` new axes)."""
        axis = dim % (cells.ndim + 1 + extra)
        if axis > cells.ndim - 1 + extra:
            raise Unsupported("row graphs cannot act along the batch axis")
        return axis

    def _take(self, cells, index):
        out = cells[index]
        return Rows(out if isinstance(out, np.ndarray) else _cell(out))

    def _op_select_int(self, shape, x, dim, i):
        c = self.cells(x)
        return self._take(c, (slice(None),) * self._axis(c, dim) + (i,))

    def _op_unbind_int(self, shape, x, dim=0):
        c = self.cells(x)
        axis = self._axis(c, dim)
        return [self._take(c, (slice(None),) * axis + (i,)) for i in range(c.shape[axis])]

    def _op_slice_Tensor(self, shape, x, dim=0, start=None, end=None, step=1):
        c = self.cells(x)
        return self._take(c, (slice(None),) * self._axis(c, dim) + (slice(start, end, step),))

    def _op_split_Tensor(self, shape, x, size, dim=0):
        c = self.cells(x)
        n = c.shape[self._axis(c, dim)]
        return [self._op_slice_Tensor(None, x, dim, s, min(s + size, n)) for s in range(0, n, size)]

    def _op_split_with_sizes_default(self, shape, x, sizes, dim=0):
        starts = np.cumsum([0, *sizes]).tolist()
        return [self._op_slice_Tensor(None, x, dim, a, b) for a, b in zip(starts, starts[1:])]

    def _op_index_select_default(self, shape, x, dim, index):
        c = self.cells(x)
        return Rows(np.take(c, index.numpy(), axis=self._axis(c, dim)))

    def _op_index_Tensor(self, shape, x, indices):
        c = self.cells(x)
        return self._take(c, tuple(slice(None) if i is None else i.numpy() for i in indices))

    def _op_unsqueeze_default(self, shape, x, dim):
        c = self.cells(x)
        return Rows(np.expand_dims(c, self._axis(c, dim, 1)))

    def _op_permute_default(self, shape, x, dims):
        if isinstance(x, Moved):  # compose: the permute of the original rows
            x, dims = x.rows, [x.dims[d % len(x.dims)] for d in dims]
        c = self.cells(x)
        dims = [d % (c.ndim + 1) for d in dims]
        if dims[-1] != c.ndim:
            return Moved(x if isinstance(x, Rows) else Rows(c), dims)
        return Rows(np.transpose(c, dims[:-1]))

    def _op_repeat_interleave_self_int(self, shape, x, repeats, dim=None, output_size=None):
        c = self.cells(x)
        return Rows(np.repeat(c, repeats, axis=self._axis(c, dim)))

    def _op_transpose_int(self, shape, x, dim0, dim1):
        c = self.cells(x)
        return Rows(np.swapaxes(c, self._axis(c, dim0), self._axis(c, dim1)))

    def _op_view_default(self, shape, x, size):
        return Rows(self.cells(x).reshape(shape[:-1]))

    _op__unsafe_view_default = _op_view_default

    def _op_expand_default(self, shape, x, size, implicit=False):
        return Rows(np.broadcast_to(self.cells(x), shape[:-1]).copy())

    def _op_clone_default(self, shape, x, **kwargs):
        return x

    def _op_alias_default(self, shape, x):
        return x

    def _op_zeros_like_default(self, shape, x, **kwargs):
        return Rows(np.full(shape[:-1], 0.0, dtype=object))

    def _op_new_zeros_default(self, shape, x, size, **kwargs):
        return self._op_zeros_like_default(shape, x)

    def _op_stack_default(self, shape, xs, dim=0):
        cells = np.broadcast_arrays(*(self.cells(x) for x in xs))
        return Rows(np.stack(cells, axis=self._axis(cells[0], dim, 1)))

    def _op_cat_default(self, shape, xs, dim=0):
        cells = [self.cells(x) for x in xs]
        return Rows(np.concatenate(cells, axis=self._axis(cells[0], dim)))

    def _reduce(self, combine, x, dims, keepdim):
        """``x`` reduced over the small axes ``dims`` by folding ``combine`` over their rows."""
        c = self.cells(x)
        axes = sorted(self._axis(c, d) for d in dims)
        kept = [a for a in range(c.ndim) if a not in axes]
        moved = np.transpose(c, kept + axes)
        moved = moved.reshape(moved.shape[:len(kept)] + (int(np.prod([c.shape[a] for a in axes])),))  # kept may be 0
        out = np.empty(moved.shape[:-1], dtype=object)
        for idx in np.ndindex(out.shape):
            terms = list(moved[idx])
            total = terms[0]
            for t in terms[1:]:
                total = combine(total, t)
            out[idx] = total
        return Rows(np.expand_dims(out, axes) if keepdim else out)

    def _op_sum_dim_IntList(self, shape, x, dims, keepdim=False, dtype=None):
        return self._reduce(_add, x, dims, keepdim)

    def _op_amax_default(self, shape, x, dims, keepdim=False):
        return self._reduce(ELEMENTWISE[aten.maximum.default], x, dims, keepdim)

    def _op_amin_default(self, shape, x, dims, keepdim=False):
        return self._reduce(ELEMENTWISE[aten.minimum.default], x, dims, keepdim)

    def _op_all_dim(self, shape, x, dim, keepdim=False):
        return self._reduce(_and, x, [dim], keepdim)

    def _op_index_copy_default(self, shape, x, dim, index, source):
        out = self.cells(x).copy()
        src = self.cells(source)
        axis = self._axis(out, dim)
        for j, i in enumerate(index.tolist()):
            out[(slice(None),) * axis + (i, Ellipsis)] = src[(slice(None),) * axis + (j, Ellipsis)]
        return Rows(out)

    def _op_index_add_default(self, shape, x, dim, index, source, alpha=1):
        out = self.cells(x).copy()
        src = self.cells(source)
        axis = self._axis(out, dim)
        for j, i in enumerate(index.tolist()):
            at = (slice(None),) * axis + (i, Ellipsis)
            out[at] = _map(lambda a, b: _add(a, b, alpha), out[at], src[(slice(None),) * axis + (j, Ellipsis)])
        return Rows(out)


#: The batch size a row graph is traced at. Every size equal to it in the traced graph is then replaced by the
#: inputs' batch size, so that one graph serves every batch: a prime that no model axis is likely to have, so that
#: no other size is mistaken for it (a constant of this size left in the graph raises instead).
TRACE_BATCH = 1031


def row_graph(fn, args: list) -> GraphModule:
    """``fn(*args) -> tuple of tensors``, for lanes tensors ``args`` (``None`` passes through), as a graph of row
    ops with the same inputs and outputs, for any batch size: the last axis of the ``per_env`` inputs. Traced once
    at ``args``' other shapes; tensors ``fn`` closes over become constants."""
    # traced on copies of env 0 at TRACE_BATCH envs: the physics has no data-dependent branches, so only the
    # shapes matter, and those of env 0 keep every intermediate finite
    probes = [_probe(x) for x in args]
    with spatial.component_formulas():  # the per-component forms torch.compile traces
        lanes_graph = _make_fx(fn, probes)
    lanes_graph.graph.eliminate_dead_code()
    outputs = fn(*probes)

    def rows_fn(*inputs):
        rows = [x if x is None else Rows(_input_cells(x)) for x in inputs]
        results = _RowInterpreter(lanes_graph).run(*rows)
        return tuple(_stack_rows(r.cells, like) for r, like in zip(results, outputs))

    graph = _make_fx(rows_fn, probes)
    graph.graph.eliminate_dead_code()
    # drop the constants that folding left unused: inductor passes every buffer to the compiled code, and ~190
    # unused ones cost ~45 us of a ~70 us call at a small batch
    used = {node.target for node in graph.graph.nodes if node.op == "get_attr"}
    for name in [name for name, _ in graph.named_buffers() if name not in used]:
        delattr(graph, name)
    _batch_sizes_symbolic(graph, args)
    for node in graph.graph.nodes:  # every constant its own storage: a higher-order op rejects aliased inputs
        if node.op == "get_attr" and isinstance(getattr(graph, node.target), torch.Tensor):
            setattr(graph, node.target, getattr(graph, node.target).clone())
    graph.recompile()
    return graph


def _make_fx(fn, probes: list) -> GraphModule:
    """``make_fx(fn)(*probes)``, with one fake-tensor mode for the metadata of every value it records: without one
    in the tracing context, make_fx creates a mode per op, each capturing a Python stack trace (half the time of
    tracing the Ant's step: 18.8 s against 10.1 s to build its kernel)."""
    with tracing(TracingContext(FakeTensorMode(allow_fallback_kernels=True))):
        return make_fx(fn)(*probes)


def _probe(x: torch.Tensor | None) -> torch.Tensor | None:
    """A per-env input as ``TRACE_BATCH`` copies of its env 0; others as they are."""
    return x[..., :1].expand(*x.shape[:-1], TRACE_BATCH).contiguous() if per_env(x) else x


def _batch_sizes_symbolic(graph: GraphModule, args: list) -> None:
    """Replace ``TRACE_BATCH`` in the size arguments of ``graph``'s ops (views, expands, fills) by the batch size
    of its first ``per_env`` input, read when the graph runs."""
    for node in list(graph.graph.nodes):
        constant = getattr(graph, node.target) if node.op == "get_attr" else None
        if isinstance(constant, torch.Tensor) and TRACE_BATCH in constant.shape:
            if constant.numel():
                raise Unsupported("row graphs cannot hold a constant with a batch axis (one value per env)")
            # an empty one (a model without hinges has no hinge rows): one env's, expanded to the batch's size when
            # the graph runs
            setattr(graph, node.target, constant[..., :1].clone())
            with graph.graph.inserting_after(node):
                empty = graph.graph.call_function(aten.expand.default, (node, list(constant.shape)))
            node.replace_all_uses_with(empty, delete_user_cb=lambda user: user is not empty)
    first = next((i for i, x in enumerate(args) if per_env(x)), None)
    if first is None:  # a batch of one env: nothing to replace
        return
    placeholder = [n for n in graph.graph.nodes if n.op == "placeholder"][first]
    with graph.graph.inserting_after(placeholder):
        batch = graph.graph.call_function(aten.sym_size.int, (placeholder, args[first].ndim - 1))

    def sizes(a):
        if isinstance(a, (list, tuple)):
            return type(a)(batch if type(v) is int and v == TRACE_BATCH else sizes(v) for v in a)
        return a

    for node in graph.graph.nodes:
        if node.op == "call_function" and node is not batch:
            node.args = tuple(sizes(a) for a in node.args)
            node.kwargs = {k: sizes(v) for k, v in node.kwargs.items()}


def _input_cells(x: torch.Tensor) -> np.ndarray:
    rows = x.reshape(-1, x.shape[-1]).unbind(0)
    cells = np.empty(len(rows), dtype=object)
    cells[:] = list(rows)
    return cells.reshape(x.shape[:-1])


def _stack_rows(cells: np.ndarray, like: torch.Tensor) -> torch.Tensor:
    """Rows back into a tensor shaped like ``like``; stacked level by level, so no output is a view."""
    def row(r):
        if _is_num(r):
            return torch.full(like.shape[-1:], r, dtype=like.dtype, device=like.device)
        return r.expand(like.shape[-1]) if r.shape[-1] != like.shape[-1] else r

    if cells.ndim == 0:
        return row(cells[()]).clone()
    if cells.size == 0:  # an empty output (a model without hinge dofs: (0, B) rates)
        return torch.zeros_like(like)
    return torch.stack([row(r) if cells.ndim == 1 else _stack_rows(r, like[0]) for r in cells])
