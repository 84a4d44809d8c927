"""Row graphs: a lanes-layout function rewritten so that every op acts on one row of ``B`` envs.

In the lanes layout (``torchsim.lanes``) a tensor is ``(*S, B)``: a few small static axes ``S`` (components,
bodies, joints) in front of the batch. A row graph unrolls ``S``: each tensor becomes an array of ``(B,)`` rows, so
gathers, concatenations, index sums and views become bookkeeping at trace time, and the model's constants fold into
the arithmetic (a joint mode of 0 removes the terms it multiplies). What is left is a straight line of elementwise
ops on rows, which ``program`` lowers to its row-op contract and the emitters turn into one loop over the batch whose
intermediates stay in registers.

How: the function runs once on lanes tensors (``_Lanes``) whose values are arrays of rows. Every aten op on them
runs the interpreter's rule for that op (``_RowOps``): views and indexing rearrange the arrays, elementwise ops map
over their elements, and each op on rows is recorded as a node of the row graph (``_Builder``), with the metadata
``program`` reads. No graph of lanes ops is traced first: the articulated Ant's step (~120k lanes ops, ~160k row
ops) is recorded in ~15 s, against ~100 s through two ``make_fx`` traces.

Tensors the function closes over (the System's shared values) are baked into the graph as constants; per-env
parameters enter as lanes inputs. The small axes are static; the batch size is not, so one graph serves a training
batch and a small evaluation batch alike.

The module runs past 400 lines because its parts are one mechanism: the interpreter's rule for each aten op on
rows, the lanes tensors that route ops to it, and the builder that records what it does.
"""

import math
import operator

import numpy as np
import torch
from torch.fx import GraphModule

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
    """A lanes tensor ``(*S, B)`` as an object array of shape ``S`` whose elements are rows (:class:`_Row`: ``(B,)``
    or ``(1,)`` values of the graph being built), or Python numbers where the value is a model constant."""

    def __init__(self, cells: np.ndarray):
        self.cells = cells


class _Builder:
    """The row graph being built: an FX graph whose nodes are recorded directly, each with its value's metadata (a
    meta tensor, as ``make_fx`` records them; computed once per distinct signature)."""

    def __init__(self):
        self.graph = torch.fx.Graph()
        self.metas: dict = {}  # an op's result metadata by its arguments' shapes and dtypes

    def call(self, op, args: tuple, kwargs: dict | None = None) -> "_Row":
        kwargs = kwargs or {}
        node = self.graph.create_node("call_function", op, _nodes(args), _nodes(kwargs),
                                      name=op.__name__.split(".")[0])  # as make_fx names them: mul, mul_1, ...
        node.meta["val"] = self.meta(op, args, kwargs)
        return _Row(self, node)

    def meta(self, op, args: tuple, kwargs: dict):
        """``op``'s result metadata for these arguments (rows, lanes tensors, constants), by running it on meta
        tensors once per signature."""
        key = (op, _signature(args), _signature(kwargs))
        if key not in self.metas:
            on_meta = {k: "meta" if k == "device" else v for k, v in kwargs.items()}
            self.metas[key] = op(*_metas(args), **_metas(on_meta))
        return self.metas[key]

    def input(self, name: str, probe: torch.Tensor | None) -> np.ndarray | None:
        """A placeholder for the input whose metadata is ``probe``, and its rows: a view as ``(rows, B)`` unbound
        (what ``reshape`` and ``unbind`` record for a contiguous tensor, the form ``program`` reads)."""
        node = self.graph.placeholder(name)
        node.meta["val"] = probe
        if probe is None:
            return None
        if not probe.is_contiguous():
            raise Unsupported("row graphs read contiguous inputs")
        flat = self.call(aten.view.default, (_Row(self, node), [-1 if probe.numel() else 0, probe.shape[-1]]))
        rows = self.graph.call_function(aten.unbind.int, (flat.node,))
        rows.meta["val"] = list(flat.node.meta["val"].unbind(0))
        cells = np.empty(len(rows.meta["val"]), dtype=object)
        for i in range(len(cells)):
            item = self.graph.call_function(operator.getitem, (rows, i))
            item.meta["val"] = rows.meta["val"][i]
            cells[i] = _Row(self, item)
        return cells.reshape(probe.shape[:-1])

    def constant(self, value: torch.Tensor) -> "_Row":
        """A row that differs between envs although no input holds it (a constant with a batch axis): kept as a
        node only so that the graph can refuse it if it is used."""
        node = self.graph.get_attr("per_env_constant")
        node.meta["val"] = torch.empty_like(value, device="meta")
        return _Row(self, node)


class _Row:
    """One row of the graph being built: Python's operators on it record the aten ops that torch's tensor operators
    dispatch to (``2 - x`` is ``rsub``, ``2 / x`` a reciprocal times 2), so the graph holds the ops a traced one
    would."""

    __slots__ = ("builder", "node")

    def __init__(self, builder: _Builder, node: torch.fx.Node):
        self.builder, self.node = builder, node

    @property
    def shape(self) -> torch.Size:
        return self.node.meta["val"].shape

    @property
    def dtype(self) -> torch.dtype:
        return self.node.meta["val"].dtype

    def __mul__(self, other):
        return _call(aten.mul.Tensor, self, other)

    def __add__(self, other):
        return _call(aten.add.Tensor, self, other)

    __rmul__, __radd__ = __mul__, __add__

    def __sub__(self, other):
        return _call(aten.sub.Tensor, self, other)

    def __rsub__(self, other):
        return _call(aten.rsub.Scalar, self, other)

    def __truediv__(self, other):
        return _call(aten.div.Tensor, self, other)

    def __rtruediv__(self, other):
        return _call(aten.mul.Tensor, _call(aten.reciprocal.default, self), other)

    def __neg__(self):
        return _call(aten.neg.default, self)

    def __and__(self, other):
        return _call(aten.bitwise_and.Tensor, self, other)

    def _compare(tensor_op, scalar_op):
        return lambda self, other: _call(tensor_op if isinstance(other, _Row) else scalar_op, self, other)

    __gt__ = _compare(aten.gt.Tensor, aten.gt.Scalar)
    __ge__ = _compare(aten.ge.Tensor, aten.ge.Scalar)
    __lt__ = _compare(aten.lt.Tensor, aten.lt.Scalar)
    __le__ = _compare(aten.le.Tensor, aten.le.Scalar)
    __ne__ = _compare(aten.ne.Tensor, aten.ne.Scalar)
    __hash__ = object.__hash__
    del _compare


def _call(op, *args, **kwargs) -> _Row:
    """``op`` recorded on rows (and numbers)."""
    builder = next(x.builder for x in args if isinstance(x, _Row))
    return builder.call(op, args, kwargs)


def _scalar(builder: _Builder, value, like: _Row | None) -> _Row:
    """A number where an op takes a tensor: a 0-d tensor of ``like``'s dtype (bools stay masks)."""
    dtype = torch.bool if isinstance(value, bool) else like.dtype if like is not None else torch.get_default_dtype()
    return builder.call(aten.scalar_tensor.default, (value,), {"dtype": dtype, "layout": torch.strided,
                                                                "device": torch.device("cpu")})


def _leaves(leaf, x):
    """``leaf`` applied to every value in ``x``'s lists, tuples and dicts (an op's arguments)."""
    if isinstance(x, (list, tuple)):
        return type(x)(_leaves(leaf, v) for v in x)
    if isinstance(x, dict):
        return {k: _leaves(leaf, v) for k, v in x.items()}
    return leaf(x)


def _nodes(x):
    """``x`` with its rows as their FX nodes."""
    return _leaves(lambda v: v.node if isinstance(v, _Row) else v, x)


def _metas(x):
    """``x`` with its rows, lanes tensors and constants as meta tensors; 0-d constants stay (a meta op takes CPU
    scalars, as a CUDA op does)."""
    def meta(v):
        if isinstance(v, _Row):
            return v.node.meta["val"]
        if isinstance(v, _Lanes):
            return v.meta
        return v.to("meta") if isinstance(v, torch.Tensor) and v.ndim else v
    return _leaves(meta, x)


def _signature(x):
    """What an op's result metadata depends on: shapes, strides and dtypes of tensors, the type of a float (the
    value of an int: it may be a dim or a size), other values."""
    if isinstance(x, (_Row, torch.Tensor)):
        meta = x.node.meta["val"] if isinstance(x, _Row) else x  # a tensor's own: no meta copy to key on
        return type(x), tuple(meta.shape), meta.stride(), meta.dtype
    if isinstance(x, (list, tuple)):
        return tuple(_signature(v) for v in x)
    if isinstance(x, dict):
        return tuple((k, _signature(v)) for k, v in sorted(x.items()))
    return float if isinstance(x, float) else x


class _Lanes(torch.Tensor):
    """A lanes tensor while a row graph is recorded: the tensor's metadata, and its value as :class:`Rows` (or
    :class:`Moved`). Every aten op on it runs the row interpreter's rule for that op (``_RowOps.call``), so the
    function runs once, on rows, with no graph of lanes ops in between."""

    @staticmethod
    def __new__(cls, value, meta: torch.Tensor, ops: "_RowOps"):
        x = torch.Tensor._make_wrapper_subclass(cls, meta.shape, strides=meta.stride(), dtype=meta.dtype,
                                                device=ops.device)
        x.value, x.meta, x.ops = value, meta, ops
        return x

    __torch_function__ = torch._C._disabled_torch_function_impl

    @classmethod
    def __torch_dispatch__(cls, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        lanes = next(x for a in (*args, *kwargs.values()) for x in (a if isinstance(a, (list, tuple)) else [a])
                     if isinstance(x, _Lanes))
        return lanes.ops.call(func, args, kwargs)


def _values(x):
    """The rows (or numbers, constants) that the lanes tensors in ``x`` hold."""
    return _leaves(lambda v: v.value if isinstance(v, _Lanes) else v, x)


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


def _unary(on_number, op):
    return lambda a: on_number(a) if _is_num(a) else _call(op, a)


def _where(cond, a, b):
    if _is_num(cond):
        return a if cond else b
    if _is_num(a) and _is_num(b) and a == b:
        return a
    like = b if isinstance(b, _Row) else a if isinstance(a, _Row) else None
    return _call(aten.where.self, cond, *(_scalar(cond.builder, x, like) if _is_num(x) else x for x in (a, b)))


def _clamp(a, lo=None, hi=None):
    if _is_num(a):
        return min(max(a, -math.inf if lo is None else lo), math.inf if hi is None else hi)
    return _call(aten.clamp.default, a, lo, *([] if hi is None else [hi]))


def _binary(on_numbers, op):
    """An op that needs rows on both sides: a number meeting a row is made a full row."""
    def fn(a, b):
        if _is_num(a) and _is_num(b):
            return on_numbers(a, b)
        a = _call(aten.full_like.default, b, a, pin_memory=False) if _is_num(a) else a
        return _call(op, a, _call(aten.full_like.default, a, b, pin_memory=False) if _is_num(b) else b)
    return fn


def _and(a, b):
    if _is_num(a) or _is_num(b):
        a, b = (a, b) if _is_num(a) else (b, a)
        return b if a else False
    return a & b


def _to(a, dtype):
    if _is_num(a):
        return float(a) if dtype.is_floating_point else bool(a) if dtype == torch.bool else int(a)
    return _call(aten._to_copy.default, a, dtype=dtype)


ELEMENTWISE = {
    aten.mul.Tensor: _mul, aten.add.Tensor: _add, aten.sub.Tensor: _sub, aten.div.Tensor: _div,
    aten.rsub.Scalar: lambda a, b, alpha=1: _sub(b, a, alpha),
    aten.neg.default: _unary(operator.neg, aten.neg.default),
    aten.rsqrt.default: _unary(lambda a: 1 / math.sqrt(a), aten.rsqrt.default),
    aten.sqrt.default: _unary(math.sqrt, aten.sqrt.default),
    aten.reciprocal.default: _unary(lambda a: 1 / a, aten.reciprocal.default),
    aten.relu.default: _unary(lambda a: max(a, 0.0), aten.relu.default),
    aten.cos.default: _unary(math.cos, aten.cos.default),
    aten.sin.default: _unary(math.sin, aten.sin.default),
    aten.where.self: _where,
    aten.clamp.default: _clamp,
    aten.clamp_min.default: lambda a, lo: _clamp(a, lo),
    aten.minimum.default: _binary(min, aten.minimum.default),
    aten.maximum.default: _binary(max, aten.maximum.default),
    aten.atan2.default: _binary(math.atan2, aten.atan2.default),
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
        rows = [x for x in xs if isinstance(x, _Row)]
        if not rows:
            return op(*(torch.tensor(x, dtype=torch.float64) if _is_num(x) and tensor else x
                        for x, tensor in zip(xs, takes_tensor)), **kwargs).item()
        return _call(op, *(_scalar(rows[0].builder, x, rows[0]) if _is_num(x) and tensor else x
                           for x, tensor in zip(xs, takes_tensor)), **kwargs)
    return fn


class _RowOps:
    """The row interpreter: each aten op on lanes tensors (:class:`_Lanes`) done on their rows, the row ops
    recorded into ``builder``; indexing, views and concatenations are bookkeeping on the arrays of rows."""

    def __init__(self, builder: _Builder, device: torch.device):
        self.builder, self.device = builder, device

    def call(self, func, args: tuple, kwargs: dict):
        meta = self.builder.meta(func, args, kwargs)
        result = self.run(func, _values(args), _values(kwargs), meta)
        if isinstance(meta, torch.Tensor):
            return _Lanes(result, meta, self)
        return [_Lanes(value, m, self) for value, m in zip(result, meta)]  # unbind, split

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
        flat = x.reshape(-1, x.shape[-1])
        uniform = (flat == flat[:, :1]).all(1).tolist()
        firsts = flat[:, 0].tolist()
        out = np.empty(len(flat), dtype=object)
        out[:] = [first if same else self.builder.constant(row) for row, same, first in zip(flat, uniform, firsts)]
        return out.reshape(x.shape[:-1])

    def run(self, target, args: tuple, kwargs: dict, meta):
        flat = [y for x in (*args, *kwargs.values()) for y in (x if isinstance(x, (list, tuple)) else [x])]
        if any(isinstance(x, Moved) for x in flat) and target is not aten.permute.default:
            raise Unsupported(f"row graphs keep the batch axis last ({target} on a batch-first tensor)")
        if target in ELEMENTWISE or torch.Tag.pointwise in target.tags:
            fn = ELEMENTWISE.get(target) or _pointwise(target)
            tensors = [self.cells(a) for a in args]
            return Rows(_map(lambda *xs: fn(*xs, **kwargs), *tensors))
        handler = getattr(self, "_op_" + target.__name__.replace(".", "_"), None)
        if handler is None:
            raise Unsupported(f"row graphs do not support {target}")
        return handler(tuple(meta.shape) if isinstance(meta, torch.Tensor) else None, *args, **kwargs)

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
    ops with the same inputs and outputs, for any batch size: the last axis of the ``per_env`` inputs. Recorded
    once at ``args``' other shapes; tensors ``fn`` closes over become constants."""
    # fn runs once, on lanes tensors of TRACE_BATCH envs whose values are rows: the physics has no data-dependent
    # branches, so only the shapes matter
    builder = _Builder()
    ops = _RowOps(builder, next(x.device for x in args if x is not None))
    inputs = []
    for i, x in enumerate(args):
        meta = None if x is None else _probe(x)
        cells = builder.input(f"arg{i}", meta)
        inputs.append(None if x is None else _Lanes(Rows(cells), meta, ops))
    with spatial.component_formulas():  # the per-component forms torch.compile traces
        outputs = fn(*inputs)
    builder.graph.output(_nodes(tuple(_stack_rows(builder, ops.cells(_values(x)), _metas(x), ops.device)
                                      for x in outputs)))
    builder.graph.eliminate_dead_code()
    if any(node.op == "get_attr" for node in builder.graph.nodes):
        raise Unsupported("row graphs cannot hold a constant with a batch axis (one value per env)")
    _batch_sizes_symbolic(builder.graph, args)
    return GraphModule(torch.nn.Module(), builder.graph)


def _probe(x: torch.Tensor) -> torch.Tensor:
    """The metadata of an input as recorded: a per-env one at ``TRACE_BATCH`` envs, contiguous."""
    if per_env(x):
        return torch.empty((*x.shape[:-1], TRACE_BATCH), dtype=x.dtype, device="meta")
    return x.to("meta")


def _batch_sizes_symbolic(graph: torch.fx.Graph, args: list) -> None:
    """Replace ``TRACE_BATCH`` in the size arguments of ``graph``'s ops (views, expands, fills) by the batch size
    of its first ``per_env`` input, read when the graph runs."""
    first = next((i for i, x in enumerate(args) if per_env(x)), None)
    if first is None:  # a batch of one env: nothing to replace
        return
    placeholder = [n for n in graph.nodes if n.op == "placeholder"][first]
    with graph.inserting_after(placeholder):
        batch = graph.call_function(aten.sym_size.int, (placeholder, args[first].ndim - 1))

    def sizes(a):
        if isinstance(a, (list, tuple)):
            return type(a)(batch if type(v) is int and v == TRACE_BATCH else sizes(v) for v in a)
        return a

    for node in graph.nodes:
        if node.op == "call_function" and node is not batch:
            node.args = tuple(sizes(a) for a in node.args)
            node.kwargs = {k: sizes(v) for k, v in node.kwargs.items()}


def _stack_rows(builder: _Builder, cells: np.ndarray, like: torch.Tensor, device: torch.device) -> _Row:
    """Rows back into a tensor shaped like ``like`` on ``device``; stacked level by level, so no output is a
    view."""
    batch = like.shape[-1]
    options = {"dtype": like.dtype, "device": device, "pin_memory": False}

    def row(r):
        if _is_num(r):
            return builder.call(aten.full.default, ([batch], r), options)
        return builder.call(aten.expand.default, (r, [batch])) if r.shape[-1] != batch else r

    if cells.ndim == 0:
        return builder.call(aten.clone.default, (row(cells[()]),))
    if cells.size == 0:  # an empty output (a model without hinge dofs: (0, B) rates)
        return builder.call(aten.full.default, (list(like.shape), 0.0), options)
    return builder.call(aten.stack.default, ([row(r) if cells.ndim == 1 else _stack_rows(builder, r, like[0], device)
                                              for r in cells],))
