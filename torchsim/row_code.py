"""Row graphs as generated C++: a whole step in one call, compiled by the system C++ compiler in seconds.

A row graph (``torchsim.rows``) is a straight-line program of elementwise ops on rows of ``B`` envs. Here each op
becomes one C++ statement on a vector of ``W`` envs (GCC vector extensions; ``W`` from ATen's CPU capability: 16
floats on AVX-512, 8 on AVX2), every intermediate a local variable. A :class:`Program` chains several row graphs
in one function, wired by :class:`Binding`s, with one graph repeated in a loop:

    for each block of W envs (a share of the batch per thread):
        load the block's rows of every input (any strides: batch-first state, lanes tensors)
        the graphs before the loop
        repeat `iterations` times: the loop graph; its outputs become the loop's carried rows
        the graphs after the loop; store their outputs

Inductor compiles one such graph in minutes (its code generator, for the Ant's ~7,600 ops), and each compiled call
returns to Python; GCC compiles the whole step in seconds, and a step is one call (``docs/benchmarks.md``).
Transcendental ops call SLEEF's 1-ulp vector functions (exported by ``libtorch_cpu``); square roots are IEEE's. No
fast-math and no FMA contraction: arithmetic rounds as its eager torch op does, library functions to within an ulp
or two of torch's (``tests/test_row_code.py``).

Built libraries are kept under ``torchsim.row_cache.cache_dir() / "cpp"``, keyed by the caller's digest of what the
code depends on (``torchsim.row_cache.content_key``), so a later process loads one without tracing its graphs.
"""

import ctypes
import math
import operator
import os
import pathlib
import subprocess
from typing import Callable, NamedTuple

import torch
from torch.fx import GraphModule, Node

from torchsim import progress, row_cache
from torchsim.rows import Unsupported

aten = torch.ops.aten

#: C++ for each elementwise op: a format string over its arguments (vectors ``V``, masks ``M`` or constants).
_OPS = {
    aten.add.Tensor: "({0} + {1})", aten.sub.Tensor: "({0} - {1})", aten.mul.Tensor: "({0} * {1})",
    aten.div.Tensor: "({0} / {1})", aten.neg.default: "(-{0})", aten.rsub.Scalar: "({1} - {0})",
    aten.reciprocal.default: "(T(1) / {0})", aten.sqrt.default: "vsqrt({0})", aten.abs.default: "vabs({0})",
    aten.rsqrt.default: "(T(1) / vsqrt({0}))", aten.relu.default: "sel({0} < T(0), vec(T(0)), {0})",
    aten.where.self: "sel({0}, vec({1}), vec({2}))", aten.minimum.default: "vmin(vec({0}), vec({1}))",
    aten.maximum.default: "vmax(vec({0}), vec({1}))",
    aten.gt.Scalar: "({0} > {1})", aten.gt.Tensor: "({0} > {1})", aten.lt.Scalar: "({0} < {1})",
    aten.lt.Tensor: "({0} < {1})", aten.ne.Scalar: "({0} != {1})", aten.ne.Tensor: "({0} != {1})",
    aten.eq.Scalar: "({0} == {1})", aten.eq.Tensor: "({0} == {1})", aten.le.Scalar: "({0} <= {1})",
    aten.le.Tensor: "({0} <= {1})", aten.ge.Scalar: "({0} >= {1})", aten.ge.Tensor: "({0} >= {1})",
    aten.logical_and.default: "({0} & {1})", aten.logical_or.default: "({0} | {1})",
    aten.logical_not.default: "(~{0})",
    aten.bitwise_and.Tensor: "({0} & {1})", aten.bitwise_or.Tensor: "({0} | {1})", aten.bitwise_not.default: "(~{0})",
    aten.sin.default: "SLEEF(sin)({0})", aten.cos.default: "SLEEF(cos)({0})", aten.asin.default: "SLEEF(asin)({0})",
    aten.acos.default: "SLEEF(acos)({0})", aten.atan.default: "SLEEF(atan)({0})", aten.exp.default: "SLEEF(exp)({0})",
    aten.log.default: "SLEEF(log)({0})", aten.tanh.default: "SLEEF(tanh)({0})",
    aten.atan2.default: "SLEEF(atan2)(vec({0}), vec({1}))",
}

#: Ops on bools (masks: every bit set for true) that ATen decompositions express as arithmetic (``isfinite``'s
#: ``mul``).
_MASK_OPS = {aten.mul.Tensor: "({0} & {1})", aten.add.Tensor: "({0} | {1})"}


def _is_mask(node: Node) -> bool:
    val = node.meta.get("val")
    return isinstance(val, torch.Tensor) and val.dtype == torch.bool


_PRELUDE = """
#include <cstdint>
#include <cstring>
typedef {T} T;
typedef T V __attribute__((vector_size({bytes})));
typedef {I} M __attribute__((vector_size({bytes})));
constexpr long W = {W};
#define SLEEF(f) Sleef_##f##{sleef}_u10
extern "C" {{
V Sleef_sin{sleef}_u10(V); V Sleef_cos{sleef}_u10(V); V Sleef_asin{sleef}_u10(V); V Sleef_acos{sleef}_u10(V);
V Sleef_atan{sleef}_u10(V); V Sleef_exp{sleef}_u10(V); V Sleef_log{sleef}_u10(V); V Sleef_tanh{sleef}_u10(V);
V Sleef_atan2{sleef}_u10(V, V);
}}
static inline V vec(V a) {{ return a; }}
static inline V vec(T a) {{ return V{{}} + a; }}
static inline V sel(M m, V a, V b) {{ return m ? a : b; }}
static inline M sel(M m, M a, M b) {{ return m ? a : b; }}
static inline V vsqrt(V a) {{ V r; for (long l = 0; l < W; ++l) r[l] = __builtin_sqrt{suffix}(a[l]); return r; }}
static inline V vabs(V a) {{ V r; for (long l = 0; l < W; ++l) r[l] = __builtin_fabs{suffix}(a[l]); return r; }}
// NaN in, NaN out, as torch.minimum and torch.maximum
static inline V vmin(V a, V b) {{ return ((a != a) | (b != b)) ? a + b : (a < b ? a : b); }}
static inline V vmax(V a, V b) {{ return ((a != a) | (b != b)) ? a + b : (a > b ? a : b); }}
// envs b .. b + n - 1 of a row at p (offset of env 0) with batch stride s; a partial block repeats its last env
static inline V load(const T* p, long s, long b, long n) {{
  V v;
  if (n == W && s == 1) {{ std::memcpy(&v, p + b, sizeof v); return v; }}
  for (long l = 0; l < W; ++l) v[l] = p[(b + (l < n ? l : n - 1)) * s];
  return v;
}}
static inline void store(T* p, long s, long b, long n, V v) {{
  if (n == W && s == 1) {{ std::memcpy(p + b, &v, sizeof v); return; }}
  for (long l = 0; l < n; ++l) p[(b + l) * s] = v[l];
}}
static inline M load_mask(const uint8_t* p, long s, long b, long n) {{
  M m;
  for (long l = 0; l < W; ++l) m[l] = p[(b + (l < n ? l : n - 1)) * s] ? -1 : 0;
  return m;
}}
static inline void store_mask(uint8_t* p, long s, long b, long n, M m) {{
  for (long l = 0; l < n; ++l) p[(b + l) * s] = m[l] != 0;
}}
"""


def vector_bytes() -> int:
    """The SIMD width the generated code targets: 64 bytes where ATen runs AVX-512 kernels, 32 where AVX2."""
    capability = torch.backends.cpu.get_cpu_capability()
    if capability.startswith("AVX512"):
        return 64
    if capability == "AVX2":
        return 32
    raise Unsupported(f"generated row code needs AVX2 or AVX-512 (ATen's CPU capability is {capability})")


class Tensor(NamedTuple):
    """An input or output of a :class:`Program`: a tensor whose row ``r`` (of its lanes view ``(*S, B)``) starts at
    element ``offsets[r]`` (times the batch size if ``rows_of_batch``: a contiguous lanes tensor), env ``b`` of it
    ``b * batch_stride`` further; a ``mask`` holds bools."""

    offsets: tuple[int, ...]
    batch_stride: int
    mask: bool
    rows_of_batch: bool = False

    @staticmethod
    def of(lanes_view: torch.Tensor) -> "Tensor":
        """The layout of a lanes tensor of more than one env: contiguous ``(*S, B)``, or a view of a batch-first
        tensor (``lanes.to_lanes``), whose strides do not depend on the batch size."""
        if lanes_view.shape[-1] < 2:
            raise ValueError("a layout is read from a tensor of at least two envs")
        mask = lanes_view.dtype == torch.bool
        if lanes_view.is_contiguous():
            return Tensor(tuple(range(lanes_view.shape[:-1].numel())), 1, mask, True)
        strides = lanes_view.stride()[:-1]
        offsets = [sum(i * s for i, s in zip(index, strides)) for index in _indices(lanes_view.shape[:-1])]
        if sorted(offsets) == list(range(len(offsets))) and lanes_view.stride(-1) == len(offsets):  # batch-first
            return Tensor(tuple(offsets), lanes_view.stride(-1), mask)
        raise ValueError(f"a Program reads contiguous lanes or batch-first tensors, not strides {lanes_view.stride()}")


def _indices(shape) -> list[tuple[int, ...]]:
    if not shape:
        return [()]
    return [(i, *rest) for i in range(shape[0]) for rest in _indices(shape[1:])]


#: A row of a graph's input: ``("input", k, r)`` (row ``r`` of the Program's input ``k``), ``("value", expr)``
#: (a C++ expression or a Python number), per placeholder a function of the row index.
Binding = Callable[[int], object]


class Program:
    """C++ for a chain of row graphs (see the module docstring), built statement by statement.

    ``add(graph, bindings)`` appends a graph, each of its placeholders bound to rows (``bindings[k](r)``), and
    returns its outputs, one list of row expressions per output tensor; ``loop(carried)`` opens the repeated part
    with carried rows initialised to ``carried``, and ``end_loop(rows)`` closes it, the carried rows becoming
    ``rows``; ``store(k, rows)`` writes an output tensor.
    """

    def __init__(self, dtype: torch.dtype, inputs: list[Tensor], outputs: list[Tensor]):
        if dtype not in (torch.float32, torch.float64):
            raise Unsupported(f"generated row code supports float32 and float64, not {dtype}")
        self.dtype, self.inputs, self.outputs = dtype, inputs, outputs
        self.loads, self.before, self.inside, self.after, self.stores = [], [], [], [], []
        self.section = self.before
        self.loaded, self.graphs = {}, 0
        self.carried: list[str] = []

    def input_row(self, k: int, r: int) -> str:
        """The local variable holding row ``r`` of input ``k``, loaded once per block."""
        name = f"in{k}_{r}"
        if name not in self.loaded:
            t = self.inputs[k]
            fn = "load_mask" if t.mask else "load"
            self.loads.append(f"const auto {name} = {fn}(in{k} + {_offset(t, r)}, {t.batch_stride}, b, n);")
            self.loaded[name] = True
        return name

    def add(self, graph: GraphModule, bindings: list[Binding]) -> list[list]:
        emitter = _Emitter(self, graph, bindings, prefix=f"g{self.graphs}_")
        self.graphs += 1
        return emitter.run()

    def loop(self, carried: list) -> list[str]:
        self.carried = [f"c{r}" for r in range(len(carried))]
        self.before += [f"V {c} = vec({_c(v)});" for c, v in zip(self.carried, carried)]
        self.section = self.inside
        return self.carried

    def end_loop(self, rows: list) -> None:
        # every new row first, then the carried ones: a new row may be a carried row as it was
        self.inside += [f"const V n{r} = vec({_c(v)});" for r, v in enumerate(rows)]
        self.inside += [f"c{r} = n{r};" for r in range(len(rows))]
        self.section = self.after

    def store(self, k: int, rows: list) -> None:
        t = self.outputs[k]
        for r, v in enumerate(rows):
            if t.mask:
                self.stores.append(f"store_mask(out{k} + {_offset(t, r)}, {t.batch_stride}, b, n, {_mask(v)});")
            else:
                self.stores.append(f"store(out{k} + {_offset(t, r)}, {t.batch_stride}, b, n, vec({_c(v)}));")

    def source(self) -> str:
        width = vector_bytes()
        T, I, suffix = ("float", "int32_t", "f") if self.dtype == torch.float32 else ("double", "int64_t", "")
        lanes = width // self.dtype.itemsize
        sleef = f"{'f' if self.dtype == torch.float32 else 'd'}{lanes}"
        params = [(f"const {'uint8_t' if t.mask else 'T'}*", f"in{k}") for k, t in enumerate(self.inputs)]
        params += [(f"{'uint8_t' if t.mask else 'T'}*", f"out{k}") for k, t in enumerate(self.outputs)]
        args = ", ".join(f"{kind} __restrict {name}" for kind, name in params)
        names = ", ".join(name for _, name in params)
        block = lambda lines, indent: "\n".join(indent + line for line in lines)  # noqa: E731
        return (_PRELUDE.format(T=T, I=I, W=lanes, bytes=width, sleef=sleef, suffix=suffix)
                + f'extern "C" void run(long batch, long begin, long end, long iterations, {args}) {{\n'
                "  for (long b = begin; b < end; b += W) {\n"
                "    const long n = end - b < W ? end - b : W;\n"
                f"{block(self.loads, '    ')}\n{block(self.before, '    ')}\n"
                f"    for (long it = 0; it < iterations; ++it) {{\n{block(self.inside, '      ')}\n    }}\n"
                f"{block(self.after, '    ')}\n{block(self.stores, '    ')}\n  }}\n}}\n"
                # the batch's blocks in `shares` contiguous shares on OpenMP threads: torch's own pool (its libgomp,
                # which this library loads), so torch's ops after a step find its threads awake
                f'extern "C" void run_shared(long batch, long shares, long iterations, {args}) {{\n'
                "  const long blocks = (batch + W - 1) / W;\n"
                "  #pragma omp parallel for num_threads(shares) schedule(static, 1)\n"
                "  for (long k = 0; k < shares; ++k) {\n"
                "    const long a = blocks * k / shares * W, b = blocks * (k + 1) / shares * W;\n"
                f"    run(batch, a, b < batch ? b : batch, iterations, {names});\n"
                "  }\n}\n")


def _offset(t: Tensor, r: int) -> str:
    return f"{t.offsets[r]} * batch" if t.rows_of_batch else str(t.offsets[r])


def _c(v) -> str:
    """A row value as C++: a number becomes a constant of type T."""
    if isinstance(v, bool):
        return "(M{} - 1)" if v else "M{}"
    if isinstance(v, (int, float)):
        v = float(v)
        if math.isnan(v):
            return "T(__builtin_nan(\"\"))"
        if math.isinf(v):
            return f"T({'-' if v < 0 else ''}__builtin_inf())"
        return f"T({v!r})"
    return v


def _mask(v) -> str:
    if isinstance(v, (bool, int, float)):
        return "(M{} - 1)" if v else "M{}"
    return v


class _Emitter:
    """One graph's nodes as statements of a :class:`Program`: each node becomes a C++ local, a constant, a row
    reference or (for an unbound input tensor) a function of the row index."""

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
                if constant.numel() != 1:
                    raise Unsupported(f"generated row code holds scalar constants, not {tuple(constant.shape)}")
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
        return [self.arg(node)]

    def arg(self, a):
        if isinstance(a, Node):
            a = self.value[a]
        if isinstance(a, tuple) and a[0] == "tensor":
            raise Unsupported("generated row code uses an input tensor whole, not row by row")
        if isinstance(a, (bool, int, float, str)):
            return a
        raise Unsupported(f"generated row code cannot use the argument {a!r}")

    def call(self, node) -> None:
        target, args = node.target, node.args
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
            self.emit(node, f"sel({_c(self.arg(args[0]))}, vec(T(1)), vec(T(0)))")
        elif target is aten.clamp.default:
            x, lo, hi = (list(args) + [None, None])[:3]
            expr = _c(self.arg(x))
            if lo is not None:
                expr = f"sel({expr} < {_c(lo)}, vec({_c(lo)}), vec({expr}))"
            if hi is not None:
                expr = f"sel({expr} > {_c(hi)}, vec({_c(hi)}), vec({expr}))"
            self.emit(node, expr)
        else:
            template = _MASK_OPS.get(target) if _is_mask(node) else None
            template = template or _OPS.get(target)
            if template is None:
                raise Unsupported(f"generated row code does not support {target}")
            values = [_c(self.arg(a)) for a in args]
            alpha = node.kwargs.get("alpha", 1)
            if alpha != 1:  # add and sub: b scaled by alpha
                values[1] = f"({values[1]} * {_c(alpha)})"
            self.emit(node, template.format(*values))

    def emit(self, node, expr: str) -> None:
        name = self.prefix + node.name
        self.program.section.append(f"const auto {name} = {expr};")
        self.value[node] = name


def compiler_command() -> list[str]:
    """How generated code is compiled: the system ``g++``, no fast-math, no FMA contraction (each op rounds as its
    torch op does), the host's ISA at the vector width of :func:`vector_bytes`, linked to ``libtorch_cpu`` (SLEEF)
    and, through ``-fopenmp``, to the OpenMP runtime torch has loaded (its intra-op threads)."""
    isa = ["-march=native"] + (["-mno-avx512f"] if vector_bytes() == 32 else [])
    torch_lib = pathlib.Path(torch.__file__).parent / "lib"
    return ["g++", "-O2", "-std=c++17", "-fPIC", "-shared", "-fopenmp", "-fno-math-errno", "-ffp-contract=off", *isa,
            f"-L{torch_lib}", f"-Wl,-rpath,{torch_lib}"]


def library_path(key: str) -> pathlib.Path:
    """Where the library built for ``key`` (a digest of everything its code depends on) is kept."""
    return row_cache.cache_dir() / "cpp" / f"{key}.so"


def build(code: str, what: str, key: str) -> pathlib.Path:
    """Compile ``code`` into the library for ``key`` (``what`` names it on the console)."""
    path = library_path(key)
    path.parent.mkdir(parents=True, exist_ok=True)
    src = path.with_suffix(f".{os.getpid()}.cpp")
    src.write_text(code)
    tmp = path.with_suffix(f".{os.getpid()}.tmp")
    with progress.announce(f"{what} as C++ ({len(code) // 1024} KB)"):
        done = subprocess.run([*compiler_command(), str(src), "-o", str(tmp), "-ltorch_cpu"], capture_output=True,
                              text=True)
    if done.returncode != 0:
        raise RuntimeError(f"compiling the generated row code {src} failed:\n{done.stderr[-4000:]}")
    tmp.replace(path)  # atomic: a concurrent process sees the whole library or none
    src.unlink()
    return path


class Kernel:
    """A built :class:`Program` (its library at ``path``): ``kernel(batch, inputs, outputs, iterations)`` runs it
    on envs ``0:batch`` of tensors laid out as the Program's; batches of several blocks per thread are split between
    ``threads`` OpenMP threads (the call releases the GIL, and envs never interact, so the shares need no
    synchronisation).

    The threads are torch's intra-op pool (OpenMP), not a pool of Python threads of its own: two pools on the same
    cores take turns badly. With Python threads, a (2048, 27) reduction right after an Ant step took 208 us against
    34 us alone, and the Ant env's steps (with their transforms) ran at 0.71 of the engine's rate; on torch's pool,
    0.83 (``docs/benchmarks.md``, "The training loop")."""

    def __init__(self, path: pathlib.Path, dtype: torch.dtype, threads: int = 1):
        self.lanes = vector_bytes() // dtype.itemsize
        library = ctypes.CDLL(str(path))
        self.run, self.run_shared = library.run, library.run_shared
        self.run.restype = self.run_shared.restype = None
        self.threads = threads

    def __call__(self, batch: int, inputs: list[torch.Tensor], outputs: list[torch.Tensor], iterations: int) -> None:
        pointers = [ctypes.c_void_p(x.data_ptr()) for x in (*inputs, *outputs)]
        shares = min(self.threads, -(-batch // self.lanes) // 4)  # at least 4 blocks a share
        if shares <= 1:
            self.run(ctypes.c_long(batch), ctypes.c_long(0), ctypes.c_long(batch), ctypes.c_long(iterations), *pointers)
        else:
            self.run_shared(ctypes.c_long(batch), ctypes.c_long(shares), ctypes.c_long(iterations), *pointers)
