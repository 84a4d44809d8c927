"""A :class:`~torchsim.execution.kernel.program.Program` as C++ for the CPU: a whole step in one call, compiled by
the system C++ compiler in seconds.

Each statement becomes one C++ statement on a vector of ``W`` envs (GCC vector extensions; ``W`` from ATen's CPU
capability: 16 floats on AVX-512, 8 on AVX2, 4 elsewhere), every intermediate a local variable; a block of ``W``
envs runs the whole step, all its substeps, in registers and on the stack.

Inductor compiles the Ant's substep (~7,600 row ops) in minutes, and each compiled call returns to Python; GCC
compiles the whole step in seconds, and a step is one call (``docs/benchmarks.md``). Transcendental ops call SLEEF's
1-ulp vector functions (exported by ``libtorch_cpu``) on x86 with AVX2 or AVX-512, the C library's elsewhere; square
roots are IEEE's. No fast-math and no FMA contraction: arithmetic rounds as its eager torch op does, library
functions to within an ulp or two of torch's (``tests/test_kernel_ops.py``).

Built libraries are kept under ``cache.cache_dir() / "cpp"``, keyed by the caller's digest of what the code depends
on (``cache.content_key``), so a later process loads one without tracing its graphs.
"""

import ctypes
import functools
import math
import os
import pathlib
import platform
import subprocess
import threading

import torch

from torchsim import progress
from torchsim.execution.kernel import cache
from torchsim.execution.kernel.program import Program, Statement
from torchsim.execution.kernel.rows import Unsupported

#: C++ for each op of the contract (``program.OPS``): a format string over its arguments (vectors ``V``, masks
#: ``M`` or constants). ``v*`` are the prelude's functions.
CPP = {
    "add": "({0} + {1})", "sub": "({0} - {1})", "mul": "({0} * {1})", "div": "({0} / {1})", "neg": "(-{0})",
    "rsub": "({1} - {0})", "recip": "(T(1) / {0})", "sqrt": "vsqrt({0})", "abs": "vabs({0})",
    "rsqrt": "(T(1) / vsqrt({0}))", "relu": "sel({0} < T(0), vec(T(0)), {0})", "where": "sel({0}, vec({1}), vec({2}))",
    "min": "vmin(vec({0}), vec({1}))", "max": "vmax(vec({0}), vec({1}))",
    "gt": "({0} > {1})", "lt": "({0} < {1})", "ne": "({0} != {1})", "eq": "({0} == {1})", "le": "({0} <= {1})",
    "ge": "({0} >= {1})", "and": "({0} & {1})", "or": "({0} | {1})", "not": "(~{0})",
    "sin": "vsin({0})", "cos": "vcos({0})", "asin": "vasin({0})", "acos": "vacos({0})", "atan": "vatan({0})",
    "exp": "vexp({0})", "log": "vlog({0})", "tanh": "vtanh({0})", "atan2": "vatan2(vec({0}), vec({1}))",
    "to_float": "sel({0}, vec(T(1)), vec(T(0)))",
    "clamp_min": "sel({0} < {1}, vec({1}), vec({0}))", "clamp_max": "sel({0} > {1}, vec({1}), vec({0}))",
}
_UNARY_LIBRARY = ("sin", "cos", "asin", "acos", "atan", "exp", "log", "tanh")

aten = torch.ops.aten

_PRELUDE = """
#include <cstdint>
#include <cstring>
typedef {T} T;
typedef T V __attribute__((vector_size({bytes})));
typedef {I} M __attribute__((vector_size({bytes})));
constexpr long W = {W};
{library}
static inline V vec(V a) {{ return a; }}
static inline V vec(T a) {{ return V{{}} + a; }}
static inline V sel(M m, V a, V b) {{ return m ? a : b; }}
static inline M sel(M m, M a, M b) {{ return m ? a : b; }}
// the sign bit cleared, as torch.abs (a lane-by-lane loop stays scalar without the loop vectoriser)
static inline V vabs(V a) {{ return (V)((M)a & ~(M)(-vec(T(0)))); }}  // -vec(0): -0.0 in every lane
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
    """The SIMD width the generated code targets: 64 bytes where ATen runs AVX-512 kernels, 32 where AVX2, else 16
    (generic vectors, which GCC lowers to whatever the CPU has: SSE, NEON, or scalar code)."""
    capability = torch.backends.cpu.get_cpu_capability()
    if capability.startswith("AVX512"):
        return 64
    return 32 if capability == "AVX2" else 16


def _sleef() -> bool:
    """Whether ``libtorch_cpu`` exports SLEEF's vector functions at :func:`vector_bytes`: x86 with AVX2 or AVX-512;
    elsewhere each lane calls the C library's function (glibc's are within an ulp)."""
    return vector_bytes() > 16


def _library(dtype: torch.dtype, lanes: int) -> str:
    """The prelude's ``vsqrt`` and ``vsin`` .. ``vatan2``: the CPU's vector square root (IEEE, correctly rounded)
    and SLEEF's 1-ulp vector functions, or the C library's functions lane by lane."""
    suffix = "f" if dtype == torch.float32 else ""
    if _sleef():
        sleef = f"{'f' if dtype == torch.float32 else 'd'}{lanes}"
        bits = 8 * vector_bytes()
        intrinsic = f"_mm{bits}_sqrt_{'ps' if dtype == torch.float32 else 'pd'}"
        register = f"__m{bits}{'' if dtype == torch.float32 else 'd'}"
        lines = ["#include <immintrin.h>", f"static inline V vsqrt(V a) {{ return (V){intrinsic}(({register})a); }}"]
        lines += ['extern "C" {'] + [f"V Sleef_{f}{sleef}_u10(V);" for f in _UNARY_LIBRARY]
        lines += [f"V Sleef_atan2{sleef}_u10(V, V);", "}"]
        lines += [f"static inline V v{f}(V a) {{ return Sleef_{f}{sleef}_u10(a); }}" for f in _UNARY_LIBRARY]
        lines.append(f"static inline V vatan2(V a, V b) {{ return Sleef_atan2{sleef}_u10(a, b); }}")
    else:
        lines = [f"static inline V v{f}(V a) {{ V r; for (long l = 0; l < W; ++l) r[l] = __builtin_{f}{suffix}(a[l]); "
                  "return r; }" for f in ("sqrt", *_UNARY_LIBRARY)]
        lines.append(f"static inline V vatan2(V a, V b) {{ V r; for (long l = 0; l < W; ++l) r[l] = "
                     f"__builtin_atan2{suffix}(a[l], b[l]); return r; }}")
    return "\n".join(lines)


def source(program: Program) -> str:
    """The C++ of ``program``: ``run(batch, begin, end, iterations, inputs..., outputs...)`` steps envs
    ``begin:end``; ``run_shared(batch, shares, iterations, ...)`` the whole batch in ``shares`` OpenMP shares."""
    width, dtype = vector_bytes(), program.dtype
    T, I = ("float", "int32_t") if dtype == torch.float32 else ("double", "int64_t")
    lanes = width // dtype.itemsize
    params = [(f"const {'uint8_t' if t.mask else 'T'}*", f"in{k}") for k, t in enumerate(program.inputs)]
    params += [(f"{'uint8_t' if t.mask else 'T'}*", f"out{k}") for k, t in enumerate(program.outputs)]
    args = ", ".join(f"{kind} __restrict {name}" for kind, name in params)
    names = ", ".join(name for _, name in params)
    loads = []
    for load in program.loads:
        t = program.inputs[load.input]
        fn = "load_mask" if t.mask else "load"
        loads.append(f"const auto {load.name} = {fn}(in{load.input} + {t.offset_code(load.row)}, {t.batch_stride}, b, "
                     "n);")
    before = [_statement(x) for x in program.before]
    before += [f"V {c} = vec({_c(v)});" for c, v in zip(program.carried, program.carried_init)]
    # every new row first, then the carried ones: a new row may be a carried row as it was
    inside = [_statement(x) for x in program.inside]
    inside += [f"const V n{r} = vec({_c(v)});" for r, v in enumerate(program.carried_next)]
    inside += [f"c{r} = n{r};" for r in range(len(program.carried_next))]
    after = [_statement(x) for x in program.after]
    stores = []
    for k, r, v in program.stores:
        t = program.outputs[k]
        if t.mask:
            stores.append(f"store_mask(out{k} + {t.offset_code(r)}, {t.batch_stride}, b, n, {_mask(v)});")
        else:
            stores.append(f"store(out{k} + {t.offset_code(r)}, {t.batch_stride}, b, n, vec({_c(v)}));")
    block = lambda lines, indent: "\n".join(indent + line for line in lines)  # noqa: E731
    return (_PRELUDE.format(T=T, I=I, W=lanes, bytes=width, library=_library(dtype, lanes))
            + f'extern "C" void run(long batch, long begin, long end, long iterations, {args}) {{\n'
            "  for (long b = begin; b < end; b += W) {\n"
            "    const long n = end - b < W ? end - b : W;\n"
            f"{block(loads, '    ')}\n{block(before, '    ')}\n"
            f"    for (long it = 0; it < iterations; ++it) {{\n{block(inside, '      ')}\n    }}\n"
            f"{block(after, '    ')}\n{block(stores, '    ')}\n  }}\n}}\n"
            # the batch's blocks in `shares` contiguous shares on OpenMP threads: torch's own pool (its libgomp,
            # which this library loads), so torch's ops after a step find its threads awake
            f'extern "C" void run_shared(long batch, long shares, long iterations, {args}) {{\n'
            "  const long blocks = (batch + W - 1) / W;\n"
            "  #pragma omp parallel for num_threads(shares) schedule(static, 1)\n"
            "  for (long k = 0; k < shares; ++k) {\n"
            "    const long a = blocks * k / shares * W, b = blocks * (k + 1) / shares * W;\n"
            f"    run(batch, a, b < batch ? b : batch, iterations, {names});\n"
            "  }\n}\n")


def _statement(x: Statement) -> str:
    return f"const auto {x.name} = {CPP[x.op].format(*(_c(a) for a in x.args))};"


def _c(v) -> str:
    """A row value as C++: a number becomes a constant of type T, a bool a mask."""
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


#: Sources up to this size compile with GCC's loop vectoriser; larger ones without (see :func:`compiler_command`).
LOOP_VECTORISED_UP_TO_BYTES = 2 << 20


def compiler_command(source_bytes: int = 0) -> list[str]:
    """How a source of ``source_bytes`` is compiled: the system ``g++``, no fast-math, no FMA contraction (each op
    rounds as its torch op does), the host's ISA at the vector width of :func:`vector_bytes`, linked to
    ``libtorch_cpu`` (SLEEF) and, through ``-fopenmp``, to the OpenMP runtime torch has loaded (its intra-op threads).

    A source past :data:`LOOP_VECTORISED_UP_TO_BYTES` compiles without GCC's loop vectoriser. The code is
    straight-line vector code already, and the vectoriser only reaches the prelude's lane loops (strided loads and
    stores), yet on the articulated Ant's 10 MB step it made the compile 300 s instead of 27 s (GCC 12.2, in register
    assignment) for 7 % of the step's speed; on the soft Ant's 0.9 MB, 3.5 % for a few seconds."""
    if platform.machine().lower() in ("x86_64", "amd64"):
        isa = ["-march=native"] + (["-mno-avx512f"] if vector_bytes() == 32 else [])
    else:  # generic vectors: the compiler's default target for the platform
        isa = []
    vectoriser = ["-fno-tree-loop-vectorize"] if source_bytes > LOOP_VECTORISED_UP_TO_BYTES else []
    torch_lib = pathlib.Path(torch.__file__).parent / "lib"
    return ["g++", "-O2", *vectoriser, "-std=c++17", "-fPIC", "-shared", "-fopenmp", "-fno-math-errno",
            "-ffp-contract=off", *isa, f"-L{torch_lib}", f"-Wl,-rpath,{torch_lib}"]


def settings() -> list[str]:
    """What the built code depends on besides its source (part of a kernel's cache key): the compiler command and
    the size its flags change at, the compiler's version and the CPU's instruction set (``-march=native`` code may
    not run on another CPU)."""
    return [*compiler_command(), str(LOOP_VECTORISED_UP_TO_BYTES), _compiler_version(), _cpu_flags()]


@functools.lru_cache(maxsize=None)
def _compiler_version() -> str:
    try:
        return subprocess.run([compiler_command()[0], "--version"], capture_output=True, text=True,
                              timeout=60).stdout.split("\n")[0]
    except (OSError, subprocess.TimeoutExpired):
        return "no compiler"  # building then raises Unsupported


@functools.lru_cache(maxsize=None)
def _cpu_flags() -> str:
    """The CPU's model and feature flags as the kernel reports them (Linux), else what Python knows of it."""
    try:
        lines = pathlib.Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return f"{platform.machine()} {platform.processor()}"
    wanted = ("model name", "flags", "Features", "CPU implementer", "CPU part")
    return "; ".join(sorted({line.strip() for line in lines if line.split(":")[0].strip() in wanted}))


def path(key: str) -> pathlib.Path:
    """Where the library built for ``key`` (a digest of everything its code depends on) is kept."""
    return cache.cache_dir() / "cpp" / f"{key}.so"


def build(code: str, what: str, key: str) -> pathlib.Path:
    """Compile ``code`` into the library for ``key`` (``what`` names it on the console). Raises ``Unsupported``
    where there is no C++ compiler (the stepper then falls back to its next strategy)."""
    path_ = path(key)
    path_.parent.mkdir(parents=True, exist_ok=True)
    unique = f"{os.getpid()}.{threading.get_ident()}"  # two threads of a process may build the same library
    src, tmp = path_.with_suffix(f".{unique}.cpp"), path_.with_suffix(f".{unique}.tmp")
    src.write_text(code)
    command = [*compiler_command(len(code)), str(src), "-o", str(tmp), "-ltorch_cpu"]
    with progress.announce(f"{what} as C++ ({len(code) // 1024} KB)"):
        try:
            done = subprocess.run(command, capture_output=True, text=True, timeout=COMPILE_TIMEOUT_S)
        except FileNotFoundError:
            src.unlink()
            raise Unsupported(f"no C++ compiler: {command[0]!r} is not on PATH") from None
        except subprocess.TimeoutExpired:
            src.unlink()
            raise Unsupported(f"the C++ compiler ran past {COMPILE_TIMEOUT_S} s") from None
    if done.returncode != 0:
        raise RuntimeError(f"compiling the generated row code {src} failed:\n{done.stderr[-4000:]}")
    cache.write(path_, tmp.read_bytes())  # with its digest, checked before every later load
    tmp.unlink()
    src.unlink()
    return path_


#: The largest shipped step (the articulated Ant's, 10 MB) compiles in ~30 s on two cores; twenty times that means
#: a stuck compiler.
COMPILE_TIMEOUT_S = 600


class Kernel:
    """A built :class:`Program` (its library at ``library_path``): ``kernel(batch, inputs, outputs, iterations)``
    runs it on envs ``0:batch`` of tensors laid out as the Program's; batches of several blocks per thread are split
    between ``threads`` OpenMP threads (the call releases the GIL, and envs never interact, so the shares need no
    synchronisation).

    The threads are torch's intra-op pool (OpenMP), not a pool of Python threads of its own: two pools on the same
    cores take turns badly. With Python threads, a (2048, 27) reduction right after an Ant step took 208 us against
    34 us alone, and the Ant env's steps (with their transforms) ran at 0.71 of the engine's rate; on torch's pool,
    0.83 (``docs/benchmarks.md``, "The training loop")."""

    def __init__(self, library_path: pathlib.Path, dtype: torch.dtype, device: torch.device, threads: int = 1):
        if torch.device(device).type != "cpu":
            raise Unsupported(f"the C++ step kernel runs on the CPU, not {device}")
        self.lanes = vector_bytes() // dtype.itemsize
        library = ctypes.CDLL(str(library_path))
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
