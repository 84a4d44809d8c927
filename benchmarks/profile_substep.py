"""Time one compiled physics substep, and with ``--stages`` each stage of the spring substep compiled alone.

The diagnostic behind the substep profile of commit 19b9828 (its ``docs/benchmarks.md``): where a substep's time goes, and what inductor's
code-generation options cost. Start: the model's first keyframe (or ``qpos0``) with a 5 cm drop and small random
velocities, random controls, fixed seed; the timed substeps continue from there. Reports the median of
``--repeats`` single substeps after 3 warm-up calls.

    python benchmarks/profile_substep.py                              # ant, spring, batch 4096, 1 thread, SIMD code
    python benchmarks/profile_substep.py --scalar --dynamic           # scalar code (cpp.simdlen=1), dynamic shapes
    python benchmarks/profile_substep.py --batch 64 --no-cpp-wrapper  # inductor's Python wrapper (default: C++)
    python benchmarks/profile_substep.py --stages                     # per-stage table (spring only)
    python benchmarks/profile_substep.py --part-sizes 4096 512 256    # the batch as parts of these sizes
    python benchmarks/profile_substep.py --count-ops                  # arithmetic per env and substep, by stage

``--part-sizes``: the batch cut into parts of each size (whole parts only), each part's substep compiled for its
size (static shapes), and a step's substeps run on one part after another on one thread, as ``torchsim.execution.parts``
does; reports the time per env and substep, interleaving the sizes over the repeats so that machine noise hits
them alike.

``--count-ops``: the element-wise arithmetic of one substep per env, in the code that ``torch.compile`` traces
(``torchsim.spatial``'s small-matrix helpers unrolled into elementwise ops), by stage (the function the substep
calls), and the compiled substep's time per element op. An op counts once per output element; a reduction
(``sum``, ``amax``) once per input element. Views, copies, gathers and concatenations are not counted.
"""

import argparse
import collections
import pathlib
import statistics
import time
import traceback
from unittest import mock

import torch

ROOT = pathlib.Path(__file__).resolve().parent.parent


def parse_args():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", default=str(ROOT / "envs" / "assets" / "ant.xml"))
    p.add_argument("--method", default="spring", choices=["spring", "xpbd"])
    p.add_argument("--batch", type=int, default=4096)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--repeats", type=int, default=15)
    p.add_argument("--scalar", action="store_true", help="scalar code (cpp.simdlen=1; default: inductor's SIMD code)")
    p.add_argument("--no-cpp-wrapper", action="store_true", help="inductor's Python wrapper around the kernels")
    p.add_argument("--dynamic", action="store_true", help="compile with dynamic shapes")
    p.add_argument("--stages", action="store_true", help="also time each stage of the spring substep alone")
    p.add_argument("--part-sizes", nargs="+", type=int, default=[], help="also time the batch cut into parts")
    p.add_argument("--count-ops", action="store_true", help="count the substep's arithmetic per env, by stage")
    return p.parse_args()


def timed(fn, args, repeats):
    """(compile seconds, median seconds per call) of ``fn(*args)``."""
    start = time.perf_counter()
    fn(*args)
    compile_s = time.perf_counter() - start
    for _ in range(3):
        fn(*args)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn(*args)
        times.append(time.perf_counter() - start)
    return compile_s, statistics.median(times)


def spring_stages(sys, bodies, q, ctrl, terms, h):
    """(name, function, args) for each stage of ``spring.substep`` (and of ``spring.step_terms``, once per step),
    with inputs computed eagerly once; ``q (nq, B)``: the bodies' coordinates."""
    from torchsim import integrator, joint_space, rigid
    from torchsim.kinematics import dof_angles, dof_values, joint_frames
    from torchsim.methods import spring

    inv = rigid.inverse_inertia(sys, bodies.x_quat, terms.inv_inertia_body)
    fr = joint_frames(sys, bodies, all_slots=False, rot=inv.rot)
    axes = dof_values(sys, fr.axes)
    angles = dof_angles(sys, dof_values(sys, fr.q), terms.window)
    force, torque = spring.joint_wrench(sys, bodies, fr, terms.joint_gain, h, inv)
    after = integrator.velocity_update(sys, bodies, inv, force, torque, h)
    return [
        ("step terms (once per step)", lambda b, q: spring.step_terms(sys, b, q, h), (bodies, q)),
        ("inverse inertias", lambda b: rigid.inverse_inertia(sys, b.x_quat, terms.inv_inertia_body), (bodies,)),
        ("joint frames", lambda b, r: joint_frames(sys, b, all_slots=False, rot=r), (bodies, inv.rot)),
        ("actuator forces", lambda b, f: spring.dof_force_wrench(sys, b, f, axes, angles, ctrl), (bodies, fr)),
        ("joint springs", lambda b, f: spring.joint_wrench(sys, b, f, terms.joint_gain, h, inv), (bodies, fr)),
        ("velocity update", lambda b, f, t: integrator.velocity_update(sys, b, inv, f, t, h), (bodies, force, torque)),
        ("armature and damping", lambda b, a, f: joint_space.inertia_and_damping(sys, b, a, f, inv, h, angles)[0],
         (bodies, after, fr)),
        ("contacts", lambda a, r: spring.contact_impulses(sys, a, terms.loaded, r), (after, inv.rot)),
        ("positions", lambda a: integrator.integrate_positions(a, h), (after,)),
    ]


def main():
    args = parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    import mujoco

    import torchsim
    from torchsim.methods import METHODS
    from torchsim.kinematics import with_world
    from torchsim.lanes import to_lanes

    sys = torchsim.load_mjcf(args.model, method=args.method).to(dtype=torch.float32)
    m = mujoco.MjModel.from_xml_path(args.model)
    q = torch.tensor(m.key_qpos[0] if m.nkey else m.qpos0, dtype=torch.float32).repeat(args.batch, 1)
    if sys.free_qpos.numel():
        q[:, sys.free_qpos[0] + 2] -= 0.05
    state = torchsim.init(sys, q, 0.1 * torch.randn(args.batch, sys.nv))
    ctrl = to_lanes(2 * torch.rand(args.batch, sys.nu) - 1).contiguous()
    bodies = with_world(*(to_lanes(x, 1) for x in state[:4]))  # the engine's lanes layout, as step makes it
    h = sys.substep_timestep
    q_lanes = to_lanes(state.q)
    terms = METHODS[args.method].step_terms(sys, bodies, q_lanes, h)  # what a step's substeps share
    options = {"cpp_wrapper": not args.no_cpp_wrapper} | ({"cpp.simdlen": 1} if args.scalar else {})

    def compiled(fn):
        return torch.compile(fn, fullgraph=True, dynamic=args.dynamic, options=options)

    print(f"{pathlib.Path(args.model).name}, {args.method}, batch {args.batch}, {args.threads} thread(s), "
          f"{'scalar' if args.scalar else 'SIMD'} code, {'Python' if args.no_cpp_wrapper else 'C++'} wrapper, "
          f"{'dynamic' if args.dynamic else 'static'} shapes, "
          f"torch {torch.__version__}")
    substep = compiled(METHODS[args.method].substep)
    compile_s, sec = timed(substep, (sys, bodies, ctrl, terms, h), args.repeats)
    print(f"substep: {sec * 1e3:.2f} ms (compile {compile_s:.0f} s)")
    if args.part_sizes:
        per_env = time_part_sizes(substep, METHODS[args.method].step_terms, sys, bodies, q_lanes, ctrl, h,
                                  args.part_sizes, args.repeats)
        for p, us in per_env.items():
            print(f"  parts of {p:5d}: {us:.2f} us per env and substep "
                  f"({1e6 / us / sys.substeps:,.0f} steps/s on this thread, substeps only)")
    if args.count_ops:
        per_stage = count_ops(METHODS[args.method].substep, (sys, bodies, ctrl, terms, h))
        total = sum(per_stage.values())
        print(f"arithmetic: {total:,.0f} element ops per env and substep; the compiled substep took "
              f"{sec / (total * args.batch) * 1e9:.3f} ns per element op")
        for stage, ops in per_stage.most_common():
            print(f"  {stage:26s} {ops:8,.0f}")
    if args.stages:
        if args.method != "spring":
            raise SystemExit("--stages times the spring substep's stages; use --method spring")
        for name, fn, fn_args in spring_stages(sys, bodies, q_lanes, ctrl, terms, h):
            compile_s, sec = timed(compiled(fn), fn_args, args.repeats)
            print(f"  {name:26s} {sec * 1e3:7.2f} ms (compile {compile_s:.0f} s)")


_ARITHMETIC = {
    "abs", "add", "asin", "atan2", "bitwise_and", "bitwise_not", "bitwise_or", "clamp", "clamp_max", "clamp_min",
    "cos", "div", "eq", "exp", "ge", "gt", "index_add", "le", "logical_and", "logical_not", "logical_or", "lt",
    "maximum", "minimum", "mul", "ne", "neg", "reciprocal", "relu", "rsqrt", "rsub", "sign", "sin", "sqrt", "sub",
    "where"}
_REDUCTIONS = {"amax", "amin", "mean", "sum"}


def count_ops(substep, args) -> collections.Counter:
    """Element ops per env of ``substep(*args)``, by the ``torchsim`` function the substep called them from.

    The substep is traced to an FX graph (the ops ``torch.compile`` sees) and dead code is removed first, as inductor
    removes it: results nothing reads (e.g. joint fields that only a step's end or the other method uses) do not
    count. Each graph node's stage comes from the Python stack of the op that made it."""
    from torch.fx.experimental.proxy_tensor import make_fx
    from torch.utils._python_dispatch import TorchDispatchMode

    sys, bodies, ctrl, terms, h = args
    stages = []  # (op, stage) of every op dispatched while tracing, in the order the graph's nodes are made

    class Stage(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, op_args=(), kwargs=None):
            frames = [f for f in traceback.extract_stack() if "/torchsim/" in f.filename]
            stages.append((func, frames[1].name if len(frames) > 1 else frames[0].name))
            return func(*op_args, **(kwargs or {}))

    def traced(b, c):
        with Stage():
            return substep(sys, b, c, terms, h)

    with mock.patch("torchsim.spatial._compiling", return_value=True):  # the paths torch.compile traces
        graph = make_fx(traced)(bodies, ctrl).graph
    nodes = [n for n in graph.nodes if isinstance(n.target, torch._ops.OpOverload)]  # not tuples' getitem
    # make_fx records a tensor constant's lift_fresh as lift_fresh_copy; every other node is the op dispatched
    if len(nodes) != len(stages) or any(n.target != func and "lift_fresh" not in str(func)
                                        for n, (func, _) in zip(nodes, stages)):
        raise RuntimeError("the traced graph's ops do not line up with the dispatched ops")
    stage_of = {n: stage for n, (_, stage) in zip(nodes, stages)}
    graph.eliminate_dead_code()
    per_stage = collections.Counter()
    for node in graph.nodes:
        name = getattr(node.target, "__name__", "").split(".")[0]
        if node.op == "call_function" and (name in _ARITHMETIC or name in _REDUCTIONS):
            counted = node.args[0] if name in _REDUCTIONS else node
            per_stage[stage_of[node]] += counted.meta["val"].numel() / ctrl.shape[-1]
    return per_stage


def time_part_sizes(substep, step_terms, sys, bodies, q, ctrl, h, sizes, repeats):
    """Microseconds per env and substep with the batch cut into whole parts of each of ``sizes`` (each part's
    ``step_terms`` built once, untimed)."""
    from torchsim.kinematics import Bodies

    def part(a, p):
        part_bodies = Bodies(*(x[..., a:a + p].contiguous() for x in bodies))
        return part_bodies, ctrl[..., a:a + p].contiguous(), step_terms(sys, part_bodies, q[..., a:a + p], h)

    batch = ctrl.shape[-1]
    jobs = {p: [part(a, p) for a in range(0, batch - p + 1, p)] for p in sizes}
    times = {p: [] for p in sizes}
    for p in sizes:
        substep(sys, *jobs[p][0][:2], jobs[p][0][2], h)  # compile this size
    for _ in range(repeats):
        for p in sizes:
            start = time.perf_counter()
            for part_bodies, part_ctrl, terms in jobs[p]:  # a step's substeps on each part, as a step in parts runs them
                for _ in range(sys.substeps):
                    part_bodies = substep(sys, part_bodies, part_ctrl, terms, h)
            times[p].append((time.perf_counter() - start) / (p * len(jobs[p]) * sys.substeps))
    return {p: statistics.median(t) * 1e6 for p, t in times.items()}


if __name__ == "__main__":
    main()
