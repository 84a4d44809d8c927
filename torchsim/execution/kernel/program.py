"""A step as one straight-line program of row ops, the description that every kernel backend emits code from.

A row graph (``rows.row_graph``) is an FX graph of elementwise aten ops on rows of ``B`` envs. A :class:`Program`
chains several row graphs, wired by :class:`Binding`s, with one graph repeated in a loop, and lowers their ops to
the small vocabulary :data:`ROW_OPS` names: statements ``name = op(args)``, each argument a statement's name, an
input row or a Python number. Its shape is that of a step:

    for each block of envs (a C++ vector of W envs; one env a CUDA thread):
        load the block's rows of every input (any strides: batch-first state, lanes tensors)
        the statements before the loop
        repeat `iterations` times: the loop's statements; their results become the loop's carried rows
        the statements after the loop; store the outputs' rows

``emit_cpp`` turns a Program into C++ for the CPU, ``emit_cuda`` into a CUDA kernel for the GPU: one
description of the step, two code generators, each with a template for every op of :data:`ROW_OPS` (the
contract: a test checks both cover it). An aten op outside it raises :class:`Unsupported` while the Program is
built, before anything runs, and ``torchsim.Stepper`` then falls back to its next strategy with one warning.
"""

import operator
from typing import Callable, NamedTuple

import torch
from torch.fx import GraphModule, Node

from torchsim.execution.kernel.rows import Unsupported

aten = torch.ops.aten

#: The row-op contract: each aten op a Program lowers, and the op it becomes. Arguments are rows of the dtype
#: ``T`` (floats), masks (bools) or numbers. Library functions (``sqrt`` and after) must be correctly rounded or
#: within a few ulps of torch's; everything else rounds as its torch op does.
ROW_OPS = {
    aten.add.Tensor: "add", aten.sub.Tensor: "sub", aten.mul.Tensor: "mul", aten.div.Tensor: "div",
    aten.neg.default: "neg", aten.rsub.Scalar: "rsub", aten.reciprocal.default: "recip", aten.abs.default: "abs",
    aten.relu.default: "relu", aten.where.self: "where", aten.minimum.default: "min", aten.maximum.default: "max",
    aten.gt.Scalar: "gt", aten.gt.Tensor: "gt", aten.lt.Scalar: "lt", aten.lt.Tensor: "lt",
    aten.ne.Scalar: "ne", aten.ne.Tensor: "ne", aten.eq.Scalar: "eq", aten.eq.Tensor: "eq",
    aten.le.Scalar: "le", aten.le.Tensor: "le", aten.ge.Scalar: "ge", aten.ge.Tensor: "ge",
    aten.logical_and.default: "and", aten.logical_or.default: "or", aten.logical_not.default: "not",
    aten.bitwise_and.Tensor: "and", aten.bitwise_or.Tensor: "or", aten.bitwise_not.default: "not",
    aten.sqrt.default: "sqrt", aten.rsqrt.default: "rsqrt", aten.sin.default: "sin", aten.cos.default: "cos",
    aten.asin.default: "asin", aten.acos.default: "acos", aten.atan.default: "atan", aten.exp.default: "exp",
    aten.log.default: "log", aten.tanh.default: "tanh", aten.atan2.default: "atan2",
}
#: Ops on masks that ATen decompositions express as arithmetic (``isfinite``'s ``mul``).
MASK_OPS = {aten.mul.Tensor: "and", aten.add.Tensor: "or"}
#: Ops a Program makes itself: a mask as 0/1 (``_to_copy``), ``clamp``'s bounds (NaN passes through, as in torch).
OWN_OPS = ("to_float", "clamp_min", "clamp_max")
#: Every op an emitter must translate.
OPS = tuple(sorted(set(ROW_OPS.values()) | set(OWN_OPS)))


class Layout(NamedTuple):
    """An input or output of a :class:`Program`: a tensor whose row ``r`` (of its lanes view ``(*S, B)``) starts at
    element ``offsets[r]`` (times the batch size if ``rows_of_batch``: a contiguous lanes tensor), env ``b`` of it
    ``b * batch_stride`` further; a ``mask`` holds bools."""

    offsets: tuple[int, ...]
    batch_stride: int
    mask: bool
    rows_of_batch: bool = False

    @staticmethod
    def of(lanes_view: torch.Tensor) -> "Layout":
        """The layout of a lanes tensor of more than one env: contiguous ``(*S, B)``, or a view of a batch-first
        tensor (``lanes.to_lanes``), whose strides do not depend on the batch size."""
        if lanes_view.shape[-1] < 2:
            raise ValueError("a layout is read from a tensor of at least two envs")
        mask = lanes_view.dtype == torch.bool
        if lanes_view.is_contiguous():
            return Layout(tuple(range(lanes_view.shape[:-1].numel())), 1, mask, True)
        strides = lanes_view.stride()[:-1]
        offsets = [sum(i * s for i, s in zip(index, strides)) for index in _indices(lanes_view.shape[:-1])]
        if sorted(offsets) == list(range(len(offsets))) and lanes_view.stride(-1) == len(offsets):  # batch-first
            return Layout(tuple(offsets), lanes_view.stride(-1), mask)
        raise ValueError(f"a Program reads contiguous lanes or batch-first tensors, not strides {lanes_view.stride()}")

    def offset_code(self, r: int) -> str:
        """Where row ``r`` starts, in elements, as a C expression (C++ and CUDA C alike) of the batch size
        ``batch``."""
        return f"{self.offsets[r]} * batch" if self.rows_of_batch else str(self.offsets[r])


def _indices(shape) -> list[tuple[int, ...]]:
    if not shape:
        return [()]
    return [(i, *rest) for i in range(shape[0]) for rest in _indices(shape[1:])]


class Statement(NamedTuple):
    """``name = op(*args)``: ``args`` are statement or load names (str) and numbers (bool, int, float)."""

    name: str
    op: str
    args: tuple
    mask: bool  # whether the result is a mask


class Load(NamedTuple):
    """``name = row r of input k``."""

    name: str
    input: int
    row: int


#: A row of a graph's input: ``("input", k, r)`` (row ``r`` of the Program's input ``k``), ``("value", v)`` (a
#: statement's name or a number), per placeholder a function of the row index.
Binding = Callable[[int], object]


class Program:
    """A chain of row graphs lowered to statements (see the module docstring).

    ``add(graph, bindings)`` appends a graph, each of its placeholders bound to rows (``bindings[k](r)``), and
    returns its outputs, one list of rows (names or numbers) per output tensor; ``loop(carried)`` opens the repeated
    part with carried rows initialised to ``carried``, and ``end_loop(rows)`` closes it, the carried rows becoming
    ``rows``; ``store(k, rows)`` writes output ``k``.

    Read by the emitters: ``loads``, ``before``, ``carried`` (names, with their initial values ``carried_init``),
    ``inside``, ``carried_next``, ``after``, ``stores`` (``(k, r, value)``).
    """

    def __init__(self, dtype: torch.dtype, inputs: list[Layout], outputs: list[Layout]):
        if dtype not in (torch.float32, torch.float64):
            raise Unsupported(f"generated row code supports float32 and float64, not {dtype}")
        self.dtype, self.inputs, self.outputs = dtype, inputs, outputs
        self.loads: list[Load] = []
        self.before: list[Statement] = []
        self.inside: list[Statement] = []
        self.after: list[Statement] = []
        self.section = self.before
        self.carried: list[str] = []
        self.carried_init: list = []
        self.carried_next: list = []
        self.stores: list[tuple[int, int, object]] = []
        self.masks: set[str] = set()  # names holding masks
        self.loaded: set[str] = set()
        self.graphs = 0

    def input_row(self, k: int, r: int) -> str:
        """The name holding row ``r`` of input ``k``, loaded once per block."""
        name = f"in{k}_{r}"
        if name not in self.loaded:
            self.loaded.add(name)
            self.loads.append(Load(name, k, r))
            if self.inputs[k].mask:
                self.masks.add(name)
        return name

    def add(self, graph: GraphModule, bindings: list[Binding]) -> list[list]:
        lowering = _Lowering(self, graph, bindings, prefix=f"g{self.graphs}_")
        self.graphs += 1
        return lowering.run()

    def emit(self, name: str, op: str, args: tuple, mask: bool) -> str:
        self.section.append(Statement(name, op, args, mask))
        if mask:
            self.masks.add(name)
        return name

    def loop(self, carried: list) -> list[str]:
        self.carried = [f"c{r}" for r in range(len(carried))]
        self.carried_init = list(carried)
        self.section = self.inside
        return self.carried

    def end_loop(self, rows: list) -> None:
        self.carried_next = list(rows)
        self.section = self.after

    def store(self, k: int, rows: list) -> None:
        self.stores += [(k, r, v) for r, v in enumerate(rows)]

    def is_mask(self, value) -> bool:
        return isinstance(value, bool) or (isinstance(value, str) and value in self.masks)


def _is_mask(node: Node) -> bool:
    val = node.meta.get("val")
    return isinstance(val, torch.Tensor) and val.dtype == torch.bool


#: The value of a constant without elements: an output with no rows.
_NO_ROWS = object()


class _Lowering:
    """One graph's nodes as statements of a :class:`Program`: each node becomes a statement, a number, a row
    reference or (for an input tensor) a function of the row index."""

    def __init__(self, program: Program, graph: GraphModule, bindings: list[Binding], prefix: str):
        self.program, self.graph, self.prefix = program, graph, prefix
        placeholders = [n for n in graph.graph.nodes if n.op == "placeholder"]
        if len(placeholders) != len(bindings):
            raise ValueError(f"the graph has {len(placeholders)} inputs, {len(bindings)} bindings given")
        self.value = {p: ("tensor", bind) for p, bind in zip(placeholders, bindings)}
        self.results = None

    def run(self) -> list[list]:
        for node in self.graph.graph.nodes:
            if node.op == "get_attr":
                constant = getattr(self.graph, node.target)
                if constant.numel() == 0:  # an output with no rows (a model without hinges: its hinge rows)
                    self.value[node] = _NO_ROWS
                elif constant.numel() != 1:
                    raise Unsupported(f"generated row code holds scalar constants, not {tuple(constant.shape)}")
                else:
                    self.value[node] = constant.item()
            elif node.op == "call_function":
                self.call(node)
            elif node.op == "output":
                self.results = [self.rows_of(x) for x in node.args[0]]
        return self.results

    def rows_of(self, node) -> list:
        """An output's rows in order: stacks (of stacks) of rows, or a single row (a 1-d output)."""
        if isinstance(node, Node) and node.target is aten.stack.default:
            return [row for a in node.args[0] for row in self.rows_of(a)]
        if isinstance(node, Node) and self.value[node] is _NO_ROWS:
            return []
        return [self.arg(node)]

    def arg(self, a):
        if isinstance(a, Node):
            a = self.value[a]
        if isinstance(a, tuple) and a[0] == "tensor":
            raise Unsupported("generated row code uses an input tensor whole, not row by row")
        if isinstance(a, (bool, int, float, str)):
            return float(a) if isinstance(a, int) and not isinstance(a, bool) else a
        raise Unsupported(f"generated row code cannot use the argument {a!r}")

    def call(self, node) -> None:
        target, args = node.target, node.args
        value = node.meta.get("val")
        if isinstance(value, torch.Tensor) and value.numel() == 0:  # made from, or as, a tensor with no rows
            self.value[node] = _NO_ROWS
            return
        if target in (aten.sym_size.int, aten.stack.default):
            return
        if target is aten.view.default and args[0].op == "placeholder":  # an input as (rows, B)
            self.value[node] = self.value[args[0]]
        elif target is aten.unbind.int:
            self.value[node] = self.value[args[0]]
        elif target is operator.getitem:
            row = self.value[args[0]][1](args[1])
            self.value[node] = self.program.input_row(*row[1:]) if row[0] == "input" else row[1]
        elif target in (aten.clone.default, aten.expand.default):  # a row, or a constant row made batch-wide
            self.value[node] = self.value[args[0]]
        elif target in (aten.full_like.default, aten.scalar_tensor.default, aten.full.default):
            self.value[node] = args[1] if target is not aten.scalar_tensor.default else args[0]
        elif target is aten._to_copy.default:
            dtype = node.kwargs.get("dtype")
            if dtype not in (torch.float32, torch.float64):
                raise Unsupported(f"generated row code converts masks to floats only, not to {dtype}")
            self.emit(node, "to_float", self.arg(args[0]))
        elif target is aten.clamp.default:
            x, lo, hi = (list(args) + [None, None])[:3]
            value = self.arg(x)
            if lo is not None:
                value = self.program.emit(self.prefix + node.name + "_lo", "clamp_min", (value, float(lo)), False)
            if hi is not None:
                value = self.program.emit(self.prefix + node.name + "_hi", "clamp_max", (value, float(hi)), False)
            self.value[node] = value
        else:
            op = (MASK_OPS.get(target) if _is_mask(node) else None) or ROW_OPS.get(target)
            if op is None:
                raise Unsupported(f"generated row code does not support {target}")
            values = [self.arg(a) for a in args]
            alpha = node.kwargs.get("alpha", 1)
            if alpha != 1:  # add and sub: b scaled by alpha
                values[1] = self.program.emit(self.prefix + node.name + "_alpha", "mul", (values[1], float(alpha)),
                                              False)
            self.emit(node, op, *values)

    def emit(self, node, op: str, *args) -> None:
        self.value[node] = self.program.emit(self.prefix + node.name, op, tuple(args), _is_mask(node))
