"""Time one compiled physics substep, and with ``--stages`` each stage of the spring substep compiled alone.

The diagnostic behind ``docs/benchmarks.md`` ("Speed pass 2"): where a substep's time goes, and what inductor's
code-generation options cost. Start: the model's first keyframe (or ``qpos0``) with a 5 cm drop and small random
velocities, random controls, fixed seed; the timed substeps continue from there. Reports the median of
``--repeats`` single substeps after 3 warm-up calls.

    python scripts/profile_substep.py                              # ant, spring, batch 4096, 1 thread, scalar code
    python scripts/profile_substep.py --vectorize --dynamic        # inductor's SIMD code, dynamic shapes
    python scripts/profile_substep.py --batch 64 --no-cpp-wrapper  # inductor's Python wrapper (default: C++)
    python scripts/profile_substep.py --stages                     # per-stage table (spring only)
    python scripts/profile_substep.py --layout                     # one stage in batch-first vs batch-last layout
"""

import argparse
import pathlib
import statistics
import time

import torch

ROOT = pathlib.Path(__file__).resolve().parent.parent


def parse_args():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", default=str(ROOT / "envs" / "assets" / "ant.xml"))
    p.add_argument("--method", default="spring", choices=["spring", "xpbd"])
    p.add_argument("--batch", type=int, default=4096)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--repeats", type=int, default=15)
    p.add_argument("--vectorize", action="store_true", help="inductor's SIMD code (default: cpp.simdlen=1)")
    p.add_argument("--no-cpp-wrapper", action="store_true", help="inductor's Python wrapper around the kernels")
    p.add_argument("--dynamic", action="store_true", help="compile with dynamic shapes")
    p.add_argument("--stages", action="store_true", help="also time each stage of the spring substep alone")
    p.add_argument("--layout", action="store_true",
                   help="time one stage written for the engine's (B, N, 3) layout and for a batch-last (3, N, B) one")
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


def spring_stages(sys, bodies, ctrl, inv_body, h):
    """(name, function, args) for each stage of ``spring.substep``, with inputs computed eagerly once."""
    from torchsim import integrator, joint_space, rigid
    from torchsim.kinematics import dof_values, joint_frames
    from torchsim.methods import spring

    inv = rigid.inverse_inertia(sys, bodies.x_quat, inv_body)
    fr = joint_frames(sys, bodies)
    axes = dof_values(sys, fr.axes)
    force, torque = spring.joint_wrench(sys, bodies, fr, inv, h)
    after = integrator.velocity_update(sys, bodies, inv, inv_body, force, torque, h)
    return [
        ("inverse inertias", lambda b: rigid.inverse_inertia(sys, b.x_quat, inv_body), (bodies,)),
        ("joint frames", lambda b: joint_frames(sys, b), (bodies,)),
        ("actuator and limit forces", lambda b, f, i: spring.dof_force_wrench(sys, b, f, i, axes, ctrl, h),
         (bodies, fr, inv)),
        ("joint springs", lambda b, f, i: spring.joint_wrench(sys, b, f, i, h), (bodies, fr, inv)),
        ("velocity update", lambda b, i, f, t: integrator.velocity_update(sys, b, i, inv_body, f, t, h),
         (bodies, inv, force, torque)),
        ("armature and damping", lambda b, a, f, i: joint_space.inertia_and_damping(sys, b, a, f, i, h)[0],
         (bodies, after, fr, inv)),
        ("armature-loaded inertias", lambda i: joint_space.armature_loaded_inertia(sys, i, axes), (inv,)),
        ("contacts", lambda a, i: spring.contact_impulses(sys, a, i, h), (after, inv)),
        ("positions", lambda a: integrator.integrate_positions(a, h), (after,)),
    ]


def rotated_inertia_product(x_quat, inv_inertia_body, xd_ang):
    """The engine's layout: ``R I^-1 R^T w`` and ``w x (R I^-1 R^T w)`` for ``x_quat (B, N, 4)``, ``w (B, N, 3)``."""
    from torchsim import math

    rot = math.quat_to_mat(x_quat)
    v = math.matvec(math.mm(rot, inv_inertia_body, rot.transpose(-1, -2)), xd_ang)
    return v, math.cross(xd_ang, v)


def rotated_inertia_product_batch_last(x_quat, inv_inertia_body, xd_ang):
    """The same with the batch innermost: ``x_quat (4, N, B)``, ``inv_inertia_body (3, 3, N, 1)``, ``w (3, N, B)``;
    every line is an elementwise op over contiguous rows of ``B`` envs, which SIMD lanes can take side by side."""
    w, x, y, z = x_quat.unbind(0)
    rot = [[w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
           [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
           [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z]]
    ang = xd_ang.unbind(0)
    body = [sum(rot[k][i] * ang[k] for k in range(3)) for i in range(3)]  # R^T w
    body = [sum(inv_inertia_body[i][k] * body[k] for k in range(3)) for i in range(3)]
    v = [sum(rot[i][k] * body[k] for k in range(3)) for i in range(3)]
    gyro = [ang[1] * v[2] - ang[2] * v[1], ang[2] * v[0] - ang[0] * v[2], ang[0] * v[1] - ang[1] * v[0]]
    return torch.stack(v), torch.stack(gyro)


def transposed_at_boundary(x_quat, inv_inertia_body, xd_ang):
    """:func:`rotated_inertia_product_batch_last` inside a batch-first stage: inputs and outputs transposed."""
    v, gyro = rotated_inertia_product_batch_last(x_quat.permute(2, 1, 0), inv_inertia_body.permute(1, 2, 0)[..., None],
                                                 xd_ang.permute(2, 1, 0))
    return v.permute(2, 1, 0), gyro.permute(2, 1, 0)


def compare_layouts(sys, bodies, inv_body, args):
    """Time :func:`rotated_inertia_product` in both layouts (and the batch-last one transposed at the stage's
    boundary), scalar and SIMD code, after checking they agree."""
    n = sys.num_bodies
    first = (bodies.x_quat[:, :n].contiguous(), inv_body, bodies.xd_ang[:, :n].contiguous())
    last = (first[0].permute(2, 1, 0).contiguous(), inv_body.permute(1, 2, 0)[..., None].contiguous(),
            first[2].permute(2, 1, 0).contiguous())
    as_f64 = [t.double() for t in first], [t.double() for t in last]  # the two sum in different orders
    for a, b in zip(rotated_inertia_product(*as_f64[0]), rotated_inertia_product_batch_last(*as_f64[1])):
        torch.testing.assert_close(a, b.permute(2, 1, 0))
    variants = (("batch-first (B, N, 3)", rotated_inertia_product, first),
                ("batch-last (3, N, B)", rotated_inertia_product_batch_last, last),
                ("batch-last, transposed at the boundary", transposed_at_boundary, first))
    print(f"one stage (R I^-1 R^T w and w x that), {n} bodies, batch {args.batch}, median us:")
    for code, options in (("scalar", {"cpp.simdlen": 1}), ("SIMD", None)):
        row = []
        for name, fn, fn_args in variants:
            compiled = torch.compile(fn, fullgraph=True, dynamic=args.dynamic, options=options)
            row.append(f"{name} {timed(compiled, fn_args, 10 * args.repeats)[1] * 1e6:.0f}")
        print(f"  {code:6s} code: " + ", ".join(row))


def main():
    args = parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    import mujoco

    import torchsim
    from torchsim import pipeline, rigid
    from torchsim.kinematics import with_world

    sys = torchsim.load_mjcf(args.model, method=args.method).to(dtype=torch.float32)
    m = mujoco.MjModel.from_xml_path(args.model)
    q = torch.tensor(m.key_qpos[0] if m.nkey else m.qpos0, dtype=torch.float32).repeat(args.batch, 1)
    if sys.free_qpos.numel():
        q[:, sys.free_qpos[0] + 2] -= 0.05
    state = torchsim.init(sys, q, 0.1 * torch.randn(args.batch, sys.nv))
    ctrl = 2 * torch.rand(args.batch, sys.nu) - 1
    inv_body = rigid.body_inverse_inertia(sys)
    bodies = with_world(state.x_pos, state.x_quat, state.xd_vel, state.xd_ang)
    h = sys.timestep / sys.substeps
    options = {"cpp_wrapper": not args.no_cpp_wrapper} | ({} if args.vectorize else {"cpp.simdlen": 1})

    def compiled(fn):
        return torch.compile(fn, fullgraph=True, dynamic=args.dynamic, options=options)

    print(f"{pathlib.Path(args.model).name}, {args.method}, batch {args.batch}, {args.threads} thread(s), "
          f"{'SIMD' if args.vectorize else 'scalar'} code, {'Python' if args.no_cpp_wrapper else 'C++'} wrapper, "
          f"{'dynamic' if args.dynamic else 'static'} shapes, "
          f"torch {torch.__version__}")
    if args.layout:
        compare_layouts(sys, bodies, inv_body, args)
        return
    substep = compiled(pipeline.SUBSTEP[args.method])
    compile_s, sec = timed(substep, (sys, bodies, ctrl, inv_body, h), args.repeats)
    print(f"substep: {sec * 1e3:.2f} ms (compile {compile_s:.0f} s)")
    if args.stages:
        if args.method != "spring":
            raise SystemExit("--stages times the spring substep's stages; use --method spring")
        for name, fn, fn_args in spring_stages(sys, bodies, ctrl, inv_body, h):
            compile_s, sec = timed(compiled(fn), fn_args, args.repeats)
            print(f"  {name:26s} {sec * 1e3:7.2f} ms (compile {compile_s:.0f} s)")


if __name__ == "__main__":
    main()
