"""A :class:`~torchsim.execution.kernel.program.Program` as CUDA C for NVIDIA GPUs: a whole step, all its substeps,
in one launch, one GPU thread an env.

Each thread reads its env's state where it lies (batch-first, any batch), runs the Program's statements as scalar
code, every intermediate a register (or, past the register file, thread-local memory that stays in L1), and writes
the next state. Per-env parameters are inputs; shared ones are constants in the code.

The code is compiled by NVRTC (the CUDA runtime compiler, which torch's CUDA builds ship) into a binary for the
device's architecture, kept on disk beside its source (``cache``). NVRTC 12.9 compiles the Ant's step for sm_90 in
5 s and the Humanoid's in 14 s on one core; Triton's compiler, the other route to a GPU kernel from Python, was still
in its layout passes on the Ant's after 11 minutes (``docs/benchmarks.md``).

Rounding follows the C++ kernel: divisions and square roots correctly rounded (NVRTC's default without fast-math),
no FMA contraction (``--fmad=false``: each op rounds as its torch op does), transcendental functions from CUDA's
math library (1-2 ulps).

Without a GPU, the same source compiles as C++ for the host (``__CUDACC__`` undefined: a loop over envs calls the
thread's function), with the C library's functions in place of CUDA's: that is how CI checks the generated GPU code
on every shipped model (``tests/test_kernel_ops.py``, ``tests/test_strategies.py``).
"""

import ctypes
import glob
import math
import os
import pathlib
import subprocess
import threading

import torch

from torchsim import progress
from torchsim.execution.kernel import cache
from torchsim.execution.kernel.program import Program, Statement
from torchsim.execution.kernel.rows import Unsupported

#: CUDA C for each op of the contract (``program.OPS``), over its arguments: names or literals (``T(..)`` numbers,
#: ``true``/``false`` masks); ``{f}`` is the math library's suffix for ``T`` (``f`` for float).
CUDA = {
    "add": "({0} + {1})", "sub": "({0} - {1})", "mul": "({0} * {1})", "div": "({0} / {1})", "neg": "(-{0})",
    "rsub": "({1} - {0})", "recip": "(T(1) / {0})", "sqrt": "sqrt{f}({0})", "abs": "fabs{f}({0})",
    "rsqrt": "(T(1) / sqrt{f}({0}))", "relu": "({0} < T(0) ? T(0) : {0})", "where": "({0} ? {1} : {2})",
    "min": "nan_min({0}, {1})", "max": "nan_max({0}, {1})",
    "gt": "({0} > {1})", "lt": "({0} < {1})", "ne": "({0} != {1})", "eq": "({0} == {1})", "le": "({0} <= {1})",
    "ge": "({0} >= {1})", "and": "({0} && {1})", "or": "({0} || {1})", "not": "(!{0})",
    "sin": "sin{f}({0})", "cos": "cos{f}({0})", "asin": "asin{f}({0})", "acos": "acos{f}({0})",
    "atan": "atan{f}({0})", "exp": "exp{f}({0})", "log": "log{f}({0})", "tanh": "tanh{f}({0})",
    "atan2": "atan2{f}({0}, {1})", "to_float": "({0} ? T(1) : T(0))",
    "clamp_min": "({0} < {1} ? T({1}) : {0})", "clamp_max": "({0} > {1} ? T({1}) : {0})",
}

_PRELUDE = """\
#ifdef __CUDACC__
#define POS_INF __longlong_as_double(0x7ff0000000000000ULL)
#define QUIET_NAN __longlong_as_double(0x7ff8000000000000ULL)
#else  // the host build: the C library's functions, a loop over envs in place of a grid
#include <math.h>
#define __device__
#define __forceinline__ inline
#define POS_INF HUGE_VAL
#define QUIET_NAN NAN
#endif
typedef {T} T;
// NaN in, NaN out, as torch.minimum and torch.maximum
__device__ __forceinline__ T nan_min(T a, T b) {{ return (a != a || b != b) ? a + b : (a < b ? a : b); }}
__device__ __forceinline__ T nan_max(T a, T b) {{ return (a != a || b != b) ? a + b : (a > b ? a : b); }}
"""


def source(program: Program) -> str:
    """The CUDA C of ``program``: ``step(batch, iterations, inputs..., outputs...)`` steps env ``e`` on thread
    ``e`` of the grid; on the host (no ``__CUDACC__``), ``step_host`` with the same arguments steps envs
    ``0:batch``."""
    T, f = ("float", "f") if program.dtype == torch.float32 else ("double", "")
    params = [f"const {'unsigned char' if t.mask else 'T'}* __restrict__ in{k}" for k, t in enumerate(program.inputs)]
    params += [f"{'unsigned char' if t.mask else 'T'}* __restrict__ out{k}" for k, t in enumerate(program.outputs)]
    names = ", ".join(p.rsplit(" ", 1)[1] for p in params)
    body = []
    for load in program.loads:
        t = program.inputs[load.input]
        value = f"in{load.input}[{t.offset_code(load.row)} + e * {t.batch_stride}]"
        body.append(f"const {'bool' if t.mask else 'T'} {load.name} = {value}{' != 0' if t.mask else ''};")
    body += [_statement(x, f) for x in program.before]
    body += [f"T {c} = {_c(v)};" for c, v in zip(program.carried, program.carried_init)]
    # every new row first, then the carried ones: a new row may be a carried row as it was
    loop = [_statement(x, f) for x in program.inside]
    loop += [f"const T n{r} = {_c(v)};" for r, v in enumerate(program.carried_next)]
    loop += [f"c{r} = n{r};" for r in range(len(program.carried_next))]
    body.append("for (int it = 0; it < iterations; ++it) {")
    body += ["  " + line for line in loop]
    body.append("}")
    body += [_statement(x, f) for x in program.after]
    for k, r, v in program.stores:
        t = program.outputs[k]
        value = f"(unsigned char)({_c(v)})" if t.mask else f"T({_c(v)})"
        body.append(f"out{k}[{t.offset_code(r)} + e * {t.batch_stride}] = {value};")
    args = ", ".join(params)
    return (_PRELUDE.format(T=T)
            + f"__device__ __forceinline__ void step_env(long long e, long long batch, int iterations, {args}) {{\n"
            + "".join(f"  {line}\n" for line in body) + "}\n"
            "#ifdef __CUDACC__\n"
            f'extern "C" __global__ void step(int batch, int iterations, {args}) {{\n'
            "  const long long e = (long long)blockIdx.x * blockDim.x + threadIdx.x;\n"
            f"  if (e < batch) step_env(e, batch, iterations, {names});\n"
            "}\n#else\n"
            f'extern "C" void step_host(int batch, int iterations, {args}) {{\n'
            f"  for (long long e = 0; e < batch; ++e) step_env(e, batch, iterations, {names});\n"
            "}\n#endif\n")


def _statement(x: Statement, f: str) -> str:
    return f"const auto {x.name} = {CUDA[x.op].format(*(_c(a) for a in x.args), f=f)};"


def _c(v) -> str:
    """A row value as C: a number becomes a constant of type T, a bool a mask."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        v = float(v)
        if math.isnan(v):
            return "T(QUIET_NAN)"
        if math.isinf(v):
            return f"T({'-' if v < 0 else ''}POS_INF)"
        return f"T({v!r})"
    return v


#: NVRTC's options besides the architecture: no FMA contraction (each op rounds as torch's does); divisions and
#: square roots are IEEE-rounded by default.
NVRTC_OPTIONS = ["--fmad=false", "--std=c++17", "-w"]
#: The host build's compiler command (the CPU check of the generated code): no fast-math, no FMA contraction; -O0, as
#: it runs a few steps of a few envs, where -O1 took 4x as long to compile (the Ant: 3.8 s against 1.0 s).
HOST_COMMAND = ["g++", "-O0", "-x", "c++", "-fPIC", "-shared", "-fno-math-errno", "-ffp-contract=off"]


def settings() -> list[str]:
    """What the binaries depend on besides the source (the architecture and NVRTC's version key each binary's file
    apart, :func:`binary_path`)."""
    return NVRTC_OPTIONS + HOST_COMMAND


def path(key: str) -> pathlib.Path:
    """Where the CUDA source for ``key`` is kept; its binaries lie beside it."""
    return cache.cache_dir() / "cuda" / f"{key}.cu"


def build(code: str, what: str, key: str) -> pathlib.Path:
    """Write the CUDA source ``code`` for ``key`` (``what`` names it on the console); :class:`Kernel` compiles it
    for the device it runs on."""
    source_path = path(key)
    cache.write(source_path, code.encode())
    progress.log.info("wrote %s as CUDA C (%d KB) to %s", what, len(code) // 1024, source_path)
    return source_path


class Kernel:
    """The CUDA source at ``source_path`` compiled for ``device``: ``kernel(batch, inputs, outputs, iterations)``
    runs it on envs ``0:batch`` of tensors laid out as its Program's, ``block`` threads (envs) a block. On a CUDA
    device NVRTC compiles it (once per architecture: the binary is kept beside the source); on the CPU, the host
    C++ compiler does (the check of the generated code without a GPU). Raises ``Unsupported`` where neither
    compiler can be found."""

    def __init__(self, source_path: pathlib.Path, dtype: torch.dtype, device: torch.device, block: int = 128):
        device = torch.device(device)
        self.block, self.on_gpu = block, device.type == "cuda"
        if self.on_gpu:
            self.launch = _cuda_kernel(source_path, device)
        elif device.type == "cpu":
            self.launch = _host_function(source_path)
        else:
            raise Unsupported(f"the CUDA step kernel runs on CUDA devices (or the CPU, to check it), not {device}")

    def __call__(self, batch: int, inputs: list[torch.Tensor], outputs: list[torch.Tensor], iterations: int) -> None:
        if self.on_gpu:
            self.launch(grid=(-(-batch // self.block), 1, 1), block=(self.block, 1, 1),
                        args=[batch, iterations, *inputs, *outputs])
        else:
            pointers = [ctypes.c_void_p(x.data_ptr()) for x in (*inputs, *outputs)]
            self.launch(ctypes.c_int(batch), ctypes.c_int(iterations), *pointers)


def _cuda_kernel(source_path: pathlib.Path, device: torch.device):
    """The ``step`` kernel of the source, compiled by NVRTC for ``device``'s architecture (or loaded, once built)."""
    try:
        from torch.cuda._utils import _cuda_load_module
    except ImportError as err:
        raise Unsupported(f"this torch cannot load CUDA modules ({err})") from None
    major, minor = torch.cuda.get_device_capability(device)
    nvrtc = _nvrtc()
    version = (ctypes.c_int(), ctypes.c_int())
    nvrtc.nvrtcVersion(ctypes.byref(version[0]), ctypes.byref(version[1]))
    binary_path = source_path.with_suffix(f".sm{major}{minor}.nvrtc{version[0].value}.{version[1].value}.cubin")
    if cache.verified(binary_path):
        binary = binary_path.read_bytes()
    else:
        code = source_path.read_text()
        with progress.announce(f"compiling {source_path.name} for sm_{major}{minor} with NVRTC "
                               f"({len(code) // 1024} KB)"):
            binary = _nvrtc_compile(nvrtc, code, f"sm_{major}{minor}")
        cache.write(binary_path, binary)
    with torch.cuda.device(device):
        return _cuda_load_module(binary, ["step"])["step"]


def _nvrtc() -> ctypes.CDLL:
    """NVRTC, as torch's CUDA build ships it (a ``nvidia`` wheel's library, or the CUDA toolkit's)."""
    major = (torch.version.cuda or "12").split(".")[0]
    candidates = [f"libnvrtc.so.{major}", "libnvrtc.so"]
    for root in {pathlib.Path(torch.__file__).parents[1], pathlib.Path(torch.__file__).parents[2]}:
        candidates += sorted(glob.glob(str(root / "nvidia" / "**" / "libnvrtc.so*"), recursive=True))
    for name in candidates:
        try:
            return ctypes.CDLL(name)
        except OSError:
            continue
    raise Unsupported("the CUDA step kernel needs NVRTC (libnvrtc), which this machine's torch does not ship")


def _nvrtc_compile(nvrtc: ctypes.CDLL, code: str, arch: str) -> bytes:
    """``code`` compiled for ``arch`` (``sm_90``): the binary (cubin)."""
    def check(result: int, what: str) -> None:
        if result != 0:
            nvrtc.nvrtcGetErrorString.restype = ctypes.c_char_p
            raise RuntimeError(f"NVRTC {what} failed: {nvrtc.nvrtcGetErrorString(result).decode()}")

    program = ctypes.c_void_p()
    check(nvrtc.nvrtcCreateProgram(ctypes.byref(program), code.encode(), b"step.cu", 0, None, None), "create")
    try:
        options = [f"--gpu-architecture={arch}".encode(), *(o.encode() for o in NVRTC_OPTIONS)]
        result = nvrtc.nvrtcCompileProgram(program, len(options), (ctypes.c_char_p * len(options))(*options))
        if result != 0:
            size = ctypes.c_size_t()
            nvrtc.nvrtcGetProgramLogSize(program, ctypes.byref(size))
            log = ctypes.create_string_buffer(size.value)
            nvrtc.nvrtcGetProgramLog(program, log)
            raise RuntimeError(f"NVRTC could not compile the generated step kernel:\n{log.value.decode()[-4000:]}")
        size = ctypes.c_size_t()
        check(nvrtc.nvrtcGetCUBINSize(program, ctypes.byref(size)), "nvrtcGetCUBINSize")
        binary = ctypes.create_string_buffer(size.value)
        check(nvrtc.nvrtcGetCUBIN(program, binary), "nvrtcGetCUBIN")
        return binary.raw
    finally:
        nvrtc.nvrtcDestroyProgram(ctypes.byref(program))


def _host_function(source_path: pathlib.Path):
    """``step_host`` of the source compiled for the CPU by the host C++ compiler (or loaded, once built)."""
    library_path = source_path.with_suffix(".host.so")
    if not cache.verified(library_path):
        tmp = library_path.with_suffix(f".{os.getpid()}.{threading.get_ident()}.tmp")
        command = [*HOST_COMMAND, str(source_path), "-o", str(tmp)]
        with progress.announce(f"compiling {source_path.name} for the host CPU (the GPU kernel's check)"):
            try:
                done = subprocess.run(command, capture_output=True, text=True, timeout=600)
            except FileNotFoundError:
                raise Unsupported(f"no C++ compiler: {command[0]!r} is not on PATH") from None
        if done.returncode != 0:
            raise RuntimeError(f"compiling {source_path} for the host failed:\n{done.stderr[-4000:]}")
        cache.write(library_path, tmp.read_bytes())
        tmp.unlink()
    function = ctypes.CDLL(str(library_path)).step_host
    function.restype = None
    return function
