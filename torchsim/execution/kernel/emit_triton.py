"""A :class:`~torchsim.execution.kernel.program.Program` as a Triton kernel for the GPU: a whole step, all its
substeps, in one launch.

Each Triton program instance carries ``BLOCK`` envs (one per GPU thread at ``BLOCK = 32 * num_warps``) through the
Program's statements, every intermediate a register, as ``emit_cpp``'s code carries a vector of envs on the CPU.
The kernel reads the public state where it lies (batch-first, any batch) and writes the next state; per-env
parameters are inputs, shared ones constants in the code.

Rounding follows the C++ kernel: divisions and square roots correctly rounded (``fdiv(ieee_rounding=True)``,
``sqrt_rn``; Triton's plain ``/`` and ``sqrt`` are approximate in float32 on NVIDIA GPUs), transcendental functions from libdevice (1-2
ulps), no fast-math. Triton contracts ``a * b + c`` into FMAs by default, which rounds once where torch rounds
twice: results agree with the reference step to float rounding, not bit for bit.

On a CPU, Triton's interpreter (``TRITON_INTERPRET=1``) runs the same kernel on CPU tensors, op by op in NumPy, with
NumPy's functions standing in for libdevice's (which only a GPU has): that is how CI checks the generated GPU code
(``tests/test_kernel_ops.py``, ``tests/test_strategies.py``).
"""

import importlib.util
import math
import os
import pathlib
import sys
import threading

import torch

from torchsim import progress
from torchsim.execution.kernel import cache
from torchsim.execution.kernel.program import Program, Statement
from torchsim.execution.kernel.rows import Unsupported

#: Triton for each op of the contract (``program.OPS``), over its arguments: names or literals; ``{v0}`` .. an
#: argument as a tensor (a number as a full row, for functions that take tensors only); ``{sqrt}`` the correctly
#: rounded square root (``sqrt_rn`` in float32; in float64 ``sqrt`` is).
TRITON = {
    "add": "({0} + {1})", "sub": "({0} - {1})", "mul": "({0} * {1})", "div": "tl.fdiv({v0}, {v1}, ieee_rounding=True)",
    "neg": "(-{0})", "rsub": "({1} - {0})", "recip": "tl.fdiv({ONE}, {v0}, ieee_rounding=True)", "sqrt": "{sqrt}({v0})",
    "abs": "tl.abs({v0})", "rsqrt": "tl.fdiv({ONE}, {sqrt}({v0}), ieee_rounding=True)",
    "relu": "tl.where({0} < 0.0, {ZERO}, {v0})", "where": "tl.where({0}, {v1}, {v2})",
    "min": "tl.minimum({v0}, {v1}, propagate_nan=tl.PropagateNan.ALL)",
    "max": "tl.maximum({v0}, {v1}, propagate_nan=tl.PropagateNan.ALL)",
    "gt": "({0} > {1})", "lt": "({0} < {1})", "ne": "({0} != {1})", "eq": "({0} == {1})", "le": "({0} <= {1})",
    "ge": "({0} >= {1})", "and": "({0} & {1})", "or": "({0} | {1})", "not": "(~{0})",
    "sin": "libdevice.sin({v0})", "cos": "libdevice.cos({v0})", "asin": "libdevice.asin({v0})",
    "acos": "libdevice.acos({v0})", "atan": "libdevice.atan({v0})", "exp": "libdevice.exp({v0})",
    "log": "libdevice.log({v0})", "tanh": "libdevice.tanh({v0})", "atan2": "libdevice.atan2({v0}, {v1})",
    "to_float": "tl.where({0}, {ONE}, {ZERO})",
    "clamp_min": "tl.where({0} < {1}, {v1}, {v0})", "clamp_max": "tl.where({0} > {1}, {v1}, {v0})",
}


def source(program: Program) -> str:
    """The Triton module of ``program``: ``step[grid](batch, iterations, inputs..., outputs..., BLOCK=...)`` steps
    envs ``0:batch``, ``BLOCK`` a program instance (a power of two)."""
    dtype = "tl.float32" if program.dtype == torch.float32 else "tl.float64"
    args = [f"in{k}" for k in range(len(program.inputs))] + [f"out{k}" for k in range(len(program.outputs))]
    body = ["env = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)",
            "live = env < batch",
            "clamped = tl.minimum(env, batch - 1)  # a partial block repeats its last env, as the C++ kernel does",
            f"ONE = tl.full([BLOCK], 1.0, {dtype})",
            f"ZERO = tl.full([BLOCK], 0.0, {dtype})",
            "TRUE = ONE == ONE",
            "FALSE = ONE != ONE"]
    emit = _Writer(dtype)
    for load in program.loads:
        t = program.inputs[load.input]
        value = f"tl.load(in{load.input} + {_offset(t, load.row)} + clamped * {t.batch_stride})"
        body.append(f"{load.name} = {value}{' != 0' if t.mask else ''}")
    body += [emit.statement(x) for x in program.before]
    body += [f"{c} = {emit.tensor(v)}" for c, v in zip(program.carried, program.carried_init)]
    loop = [emit.statement(x) for x in program.inside]
    # every new row first, then the carried ones: a new row may be a carried row as it was
    loop += [f"n{r} = {emit.tensor(v)}" for r, v in enumerate(program.carried_next)]
    loop += [f"c{r} = n{r}" for r in range(len(program.carried_next))]
    body.append("for _ in range(iterations):")
    body += ["    " + line for line in loop or ["pass"]]
    body += [emit.statement(x) for x in program.after]
    for k, r, v in program.stores:
        t = program.outputs[k]
        value = emit.mask(v) if t.mask else emit.tensor(v)
        body.append(f"tl.store(out{k} + {_offset(t, r)} + env * {t.batch_stride}, {value}, mask=live)")
    return ("import triton\nimport triton.language as tl\nfrom triton.language.extra import libdevice\n\n\n"
            # one compile serves every batch and substep count (Triton would specialise on their divisibility by 16)
            '@triton.jit(do_not_specialize=["batch", "iterations"])\n'
            f"def step(batch, iterations, {', '.join(args)}, BLOCK: tl.constexpr):\n"
            + "".join(f"    {line}\n" for line in body))


class _Writer:
    """Statements and values as Triton expressions."""

    def __init__(self, dtype: str):
        self.dtype = dtype

    def statement(self, x: Statement) -> str:
        literals = [_literal(a) for a in x.args]
        tensors = {f"v{i}": self.tensor(a) for i, a in enumerate(x.args)}
        sqrt = "tl.sqrt_rn" if self.dtype == "tl.float32" else "tl.sqrt"
        return f"{x.name} = {TRITON[x.op].format(*literals, ONE='ONE', ZERO='ZERO', sqrt=sqrt, **tensors)}"

    def tensor(self, v) -> str:
        """``v`` as a row tensor of the Program's dtype (a number as a full row)."""
        if isinstance(v, bool):
            return "TRUE" if v else "FALSE"
        if isinstance(v, (int, float)):
            return f"tl.full([BLOCK], {_literal(v)}, {self.dtype})"
        return v

    def mask(self, v) -> str:
        if isinstance(v, (bool, int, float)):
            return "TRUE" if v else "FALSE"
        return v


def _literal(v) -> str:
    if isinstance(v, bool):
        return "TRUE" if v else "FALSE"
    if isinstance(v, (int, float)):
        v = float(v)
        if math.isnan(v):
            return 'float("nan")'
        if math.isinf(v):
            return f'{"-" if v < 0 else ""}float("inf")'
        return repr(v)
    return v


def _offset(t, r: int) -> str:
    n, times_batch = t.offset(r)
    return f"{n} * batch" if times_batch else str(n)


def interpreting() -> bool:
    """Whether Triton runs kernels in its interpreter (``TRITON_INTERPRET=1``): on CPU tensors, op by op."""
    return os.environ.get("TRITON_INTERPRET", "0") not in ("", "0")


def settings() -> str:
    """What the kernel module depends on besides its source (part of its cache key): nothing; Triton keys the
    binaries it compiles from it on its own version and the GPU."""
    return "triton"


def path(key: str) -> pathlib.Path:
    """Where the kernel module for ``key`` is kept (Triton reads a kernel's source from its file)."""
    return cache.cache_dir() / "triton" / f"step_{key}.py"


def build(code: str, what: str, key: str) -> pathlib.Path:
    """Write the kernel module ``code`` for ``key`` (``what`` names it on the console); Triton compiles it on its
    first launch."""
    module = path(key)
    module.parent.mkdir(parents=True, exist_ok=True)
    tmp = module.with_suffix(f".{os.getpid()}.{threading.get_ident()}.tmp")
    tmp.write_text(code)
    tmp.replace(module)  # atomic: a concurrent process sees the whole module or none
    progress.log.info("wrote %s as Triton (%d KB) to %s", what, len(code) // 1024, module)
    return module


class Kernel:
    """A built Triton kernel (its module at ``module_path``, for ``dtype``): ``kernel(batch, inputs, outputs, iterations)`` runs it on
    envs ``0:batch`` of tensors laid out as the Program's, ``block`` envs a program instance on ``num_warps`` warps.
    Triton compiles it for the GPU on the first call (and keeps the binary in its own cache)."""

    def __init__(self, module_path: pathlib.Path, dtype: torch.dtype, block: int = 128, num_warps: int = 4):
        try:
            import triton  # noqa: F401  (torch's CUDA builds ship it; the CPU build does not)
        except ImportError as err:
            raise Unsupported(f"the GPU step kernel needs Triton ({err})") from None
        if block & (block - 1):
            raise ValueError(f"block must be a power of two, got {block}")
        name = f"torchsim_triton_{module_path.stem}"
        spec = importlib.util.spec_from_file_location(name, module_path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module  # Triton resolves the kernel's globals through its module
        spec.loader.exec_module(module)
        if interpreting():  # libdevice exists on GPUs only: NumPy's functions run in its place
            module.libdevice = _InterpretedLibdevice()
        self.step, self.block, self.num_warps = module.step, block, num_warps

    def __call__(self, batch: int, inputs: list[torch.Tensor], outputs: list[torch.Tensor], iterations: int) -> None:
        grid = (-(-batch // self.block),)
        if interpreting():  # NumPy warns of inf and NaN arithmetic, which a GPU (and the C++ kernel) does silently
            import numpy as np

            with np.errstate(all="ignore"):
                self.step[grid](batch, iterations, *inputs, *outputs, BLOCK=self.block)
            return
        self.step[grid](batch, iterations, *inputs, *outputs, BLOCK=self.block, num_warps=self.num_warps)


class _InterpretedLibdevice:
    """libdevice's functions for Triton's interpreter, on its NumPy-backed tensors (NumPy's functions are within an
    ulp or two of torch's)."""

    def __getattr__(self, name: str):
        import numpy as np
        import triton.language as tl
        from triton.runtime.interpreter import TensorHandle

        fn = {"asin": np.arcsin, "acos": np.arccos, "atan": np.arctan, "atan2": np.arctan2}.get(name)
        fn = fn or getattr(np, name)

        def apply(*xs):
            out = fn(*(x.handle.data for x in xs))
            return tl.tensor(TensorHandle(out, xs[0].dtype.scalar), xs[0].type)

        return apply
