"""The generated kernels (``torchsim.execution.kernel``): every op of the row-op contract, emitted as C++ (the CPU
kernel) and as CUDA C (the GPU kernel, compiled here for the host CPU: the same source, a loop over envs in place
of a grid), gives torch's own result on the same rows.

One row graph holds every op (``rows.row_graph`` of a lanes function), so one build per emitter and dtype serves the
file (a few seconds). C++ arithmetic and selections must match eager torch bit for bit (no fast-math, no FMA
contraction). Library functions may differ by an ulp or two (the bound: 4 ulps of the dtype): the generated square
root is IEEE's, correctly rounded, where torch's CPU kernel (MKL's) is within an ulp (it differs from the correctly
rounded root in ~17% of random float32 values), and the transcendental functions call SLEEF's u10 (1-ulp) vector
functions in C++ (the C library's, lane by lane, where a CPU lacks AVX2), the C library's in the CUDA kernel's host
build (CUDA's math library on a GPU). The rows hold NaN, +-inf, +-0 and values across many magnitudes, so NaN
handling (``minimum``/``maximum`` propagate it, as torch's do) and ``abs``'s sign bit are checked too; batches of 1,
5 and 37 envs cover whole and partial vector blocks, and a strided (batch-first) input. The C++ is built three
ways: for this CPU, for a CPU without AVX2, and as a step too large for GCC's loop vectoriser is.
"""

import hashlib

import pytest
import torch

import torchsim
import torchsim.envs
from torchsim import lanes
from torchsim.execution.kernel import emit_cpp, emit_cuda, program as program_module, rows
from torchsim.execution.kernel.program import Layout, Program

SPECIAL = [float("nan"), float("inf"), -float("inf"), 0.0, -0.0, 1e-30, -3.5, 2.0, 1e6]
#: ``cpp-generic``: the C++ a CPU without AVX2 gets (16-byte generic vectors, the C library's functions lane by lane);
#: ``cpp-large``: as a step past ``emit_cpp.LOOP_VECTORISED_UP_TO_BYTES`` compiles (no loop vectoriser)
EMITTERS = {"cpp": (emit_cpp, {}), "cpp-generic": (emit_cpp, {}), "cpp-large": (emit_cpp, {}),
            "cuda-host": (emit_cuda, {})}


def _ops(x: torch.Tensor, y: torch.Tensor, p: torch.Tensor):
    """Rows ``x``, ``y`` (any values) and ``p`` (in (-1, 1)) through every op the generator translates."""
    mask = x > y
    results = [x + y, x - y, x * y, x / y, -x, 2.5 - x, 1 / y, torch.sqrt(x.abs()), torch.rsqrt(y.abs()), x.abs(),
               torch.relu(x), torch.where(mask, x, y), torch.minimum(x, y), torch.maximum(x, y),
               x.clamp(-1.0, 2.0), x.clamp_min(0.5), torch.sin(p * 7), torch.cos(p * 7), torch.asin(p),
               torch.acos(p), torch.atan(x), torch.atan2(x, y), torch.exp(p * 5), torch.log(y.abs() + 0.1),
               torch.tanh(x)]
    masks = [mask, x < y, x >= y, x <= y, x == y, x != y, mask & (x > 0), mask | (y > 0), ~mask,
             torch.isfinite(x), torch.logical_and(mask, y < 0), torch.logical_or(mask, y < 0),
             torch.logical_not(mask)]
    return torch.stack(results + [m.to(x.dtype) for m in masks])


@pytest.fixture(scope="module", params=[(e, d) for e in EMITTERS for d in (torch.float32, torch.float64)],
                ids=lambda p: f"{p[0]}-{p[1]}".replace("torch.", ""))
def kernel(request, tmp_path_factory):
    name, dtype = request.param
    emitter, options = EMITTERS[name]
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("TORCHSIM_CACHE_DIR", str(tmp_path_factory.mktemp("cache")))
        if name == "cpp-generic":
            patch.setattr(emit_cpp, "vector_bytes", lambda: 16)
        if name == "cpp-large":
            patch.setattr(emit_cpp, "LOOP_VECTORISED_UP_TO_BYTES", 0)
        probe = torch.ones(3, 2, dtype=dtype)
        graph = rows.row_graph(lambda xs: (_ops(xs[0], xs[1], xs[2]),), [probe])
        outputs = _ops(probe[0], probe[1], probe[2])
        layout_in = Layout.of(probe)
        layout_out = Layout.of(outputs)
        # a second input layout: the rows of a batch-first (B, 3) tensor, as the step kernel reads the public state
        layout_strided = Layout.of(lanes.to_lanes(torch.ones(2, 3, dtype=dtype)))
        built = {}
        for layout_name, layout in (("contiguous", layout_in), ("strided", layout_strided)):
            program = Program(dtype, [layout], [layout_out])
            program.store(0, program.add(graph, [lambda r: ("input", 0, r)])[0])
            code = emitter.source(program)
            key = hashlib.sha256(repr((code, emitter.settings())).encode()).hexdigest()[:32]
            path = emitter.build(code, f"the op test ({layout_name}, {dtype})", key)
            built[layout_name] = emitter.Kernel(path, dtype, torch.device("cpu"), **options)
    return name, dtype, built, outputs.shape[0]


@pytest.mark.parametrize("batch", [1, 5, 37])
def test_every_op_matches_torch(kernel, batch):
    name, dtype, built, count = kernel
    g = torch.Generator().manual_seed(batch)
    values = torch.randn(3, batch, generator=g, dtype=torch.float64) * 10.0 ** torch.randint(-3, 4, (3, batch),
                                                                                             generator=g)
    values = values.to(dtype)
    for i, v in enumerate(SPECIAL[:batch]):  # special values in x, and in y shifted by one env
        values[0, i] = v
        values[1, (i + 1) % batch] = v
    values[2] = torch.rand(batch, generator=g, dtype=dtype) * 1.98 - 0.99
    expected = _ops(values[0], values[1], values[2])
    for layout_name, k in built.items():
        inputs = values.contiguous() if layout_name == "contiguous" else values.t().contiguous()
        out = torch.empty(count, batch, dtype=dtype)
        k(batch, [inputs], [out], 1)
        library = [7, 8] + list(range(16, 25))  # roots and transcendental functions
        exact = [i for i in range(count) if i not in library]  # arithmetic, selections, masks
        torch.testing.assert_close(out[exact], expected[exact], rtol=0, atol=0, equal_nan=True)
        ulps = torch.finfo(dtype).eps * 4
        torch.testing.assert_close(out[library], expected[library], rtol=ulps, atol=ulps, equal_nan=True)


def test_both_emitters_cover_the_contract():
    """Each emitter has a translation for every op of the row-op contract, and nothing beyond it."""
    assert set(emit_cpp.CPP) == set(program_module.OPS)
    assert set(emit_cuda.CUDA) == set(program_module.OPS)


def test_unsupported_op_is_named():
    """An op the generator has no translation for is refused by name (the stepper then falls back)."""
    probe = torch.ones(2, 2)
    graph = rows.row_graph(lambda x: (torch.erf(x),), [probe])
    program = Program(torch.float32, [Layout.of(probe)], [Layout.of(probe)])
    with pytest.raises(rows.Unsupported, match="erf"):
        program.add(graph, [lambda r: ("input", 0, r)])


def test_step_kernel_refuses_a_state_it_would_misread():
    """The step kernel reads raw memory, so a state of another dtype or model is refused by name, not misread."""
    sys = torchsim.load_mjcf(str(torchsim.envs.asset_path("inverted_pendulum.xml")))
    stepper = torchsim.Stepper(sys, "kernel")
    state = torchsim.init(sys, sys.q0.expand(3, -1).clone(), torch.zeros(3, sys.nv))
    stepper(state, torch.zeros(3, sys.nu))
    assert stepper.strategy == "kernel"
    with pytest.raises(ValueError, match=r"state.x_pos must be a torch.float32 tensor of shape \(3, 2, 3\) on cpu"):
        stepper(state._replace(x_pos=state.x_pos.double()), torch.zeros(3, sys.nu))
    with pytest.raises(ValueError, match=r"state.q must be .* of shape \(3, 2\) .* got torch.float32 \(1, 2\)"):
        stepper(state._replace(q=state.q[:1]), torch.zeros(3, sys.nu))  # a batch the code would read past


def test_step_kernel_follows_a_system_edited_in_place():
    """The kernel bakes the System's values in: editing one of its tensors in place builds a new kernel, whose steps
    equal the reference step of the edited System (float32 rounding of reordered sums: 1e-5)."""
    sys = torchsim.load_mjcf(str(torchsim.envs.asset_path("inverted_pendulum.xml")))
    stepper = torchsim.Stepper(sys, "kernel")
    state = torchsim.init(sys, sys.q0.expand(3, -1).clone(), torch.zeros(3, sys.nv))
    ctrl = torch.full((3, sys.nu), 0.5)
    before = stepper(state, ctrl)
    with torch.no_grad():
        sys.body_mass.mul_(3.0)
    after = stepper(state, ctrl)
    assert not torch.allclose(after.qd, before.qd, atol=1e-3)
    torch.testing.assert_close(after.qd, torchsim.step(sys, state, ctrl).qd, rtol=0, atol=1e-5)


def test_step_kernel_with_per_env_parameters_matches_the_reference():
    """Domain randomisation (``set_physics``: mass, contact friction and actuator gain per env) runs on the kernel,
    its per-env parameters inputs of the generated code: 10 Ant steps (contacts, so friction acts) in float64 equal
    the reference step of the same System to its rounding (1e-9; measured ~1e-12); a System with other per-env values
    (the next ``set_physics``) runs on the same built kernel, and differs from the first."""
    env = torchsim.envs.make("ant", num_envs=5)
    scales = dict(mass_scale=torch.linspace(0.5, 1.5, 5), friction_scale=torch.linspace(0.2, 2.0, 5),
                  actuator_gain_scale=torch.linspace(0.7, 1.3, 5))
    env.set_physics(**scales)
    sys = env.sys.to(dtype=torch.float64)
    stepper = torchsim.Stepper(sys)
    assert stepper.strategy == "kernel"
    q, qd = env._sample_init(5)
    start = torchsim.init(sys, q.double(), qd.double())
    ctrl = torch.rand(10, 5, sys.nu, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 2 - 1
    reference, kernel = start, start
    for u in ctrl:
        reference, kernel = torchsim.step(sys, reference, u), stepper(kernel, u)
    assert max((a - b).abs().max().item() for a, b in zip(reference[:6], kernel[:6])) < 1e-9
    other = stepper.for_system(sys.replace(body_mass=sys.body_mass.flip(0)))
    moved = other(start, ctrl[0])
    assert other._kernel_built[1] is stepper._kernel_built[1]
    assert not torch.allclose(moved.qd, stepper(start, ctrl[0]).qd)
    torch.testing.assert_close(moved.qd, torchsim.step(other.sys, start, ctrl[0]).qd, rtol=0, atol=1e-9)


def test_step_kernel_shares_a_batch_between_threads_exactly():
    """A batch of at least 4 vector blocks per thread runs in shares on torch's OpenMP threads
    (``emit_cpp.Kernel``): envs never interact, so two threads' steps equal one thread's bit for bit, across the
    shares' seam and a partial last block (8 blocks and 5 envs: shares of 4 and 5 blocks)."""
    sys = torchsim.load_mjcf(str(torchsim.envs.asset_path("inverted_pendulum.xml")))
    batch = 8 * emit_cpp.vector_bytes() // 4 + 5
    generator = torch.Generator().manual_seed(0)
    state = torchsim.init(sys, sys.q0 + 0.3 * torch.randn(batch, sys.nq, generator=generator),
                          torch.randn(batch, sys.nv, generator=generator))
    ctrl = torch.rand(batch, sys.nu, generator=generator) * 2 - 1
    one, two = torchsim.Stepper(sys, "kernel", threads=1), torchsim.Stepper(sys, "kernel", threads=2)
    a, b = state, state
    for _ in range(5):
        a, b = one(a, ctrl), two(b, ctrl)
    assert two._kernel_built[1].kernel.threads == 2
    for x, y in zip(a, b):
        assert torch.equal(x, y)
