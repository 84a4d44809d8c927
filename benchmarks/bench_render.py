"""Frames/s of torchsim.render against mujoco.Renderer on the same scene, camera and resolution, in one run.

    MUJOCO_GL=egl OMP_NUM_THREADS=1 python benchmarks/bench_render.py --env ant --size 64 --batches 1 16 64 256 1024

torchsim renders the whole batch in one call (``render`` on a State of ``B`` random poses); MuJoCo renders one
frame at a time (``update_scene`` + ``render`` per env pose, from precomputed ``MjData``; its frames/s does not
depend on the batch, so it is measured once on ``--mujoco-frames`` poses). Both time rendering only, not physics.
Times are medians of ``--repeats`` runs after a warm-up. torch uses ``torch.get_num_threads()`` threads (set
``OMP_NUM_THREADS`` or ``--threads``); MuJoCo's OpenGL renderer here is whatever ``MUJOCO_GL`` gives (EGL on a
machine without a GPU is Mesa's software rasteriser).
"""

import argparse
import os
import sys
import time

if "--no-mujoco" not in sys.argv:  # no GL context is needed (nor may be available) when MuJoCo does not render
    os.environ.setdefault("MUJOCO_GL", "egl")  # before mujoco is imported (by torchsim)

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

import torchsim  # noqa: E402
import torchsim.envs  # noqa: E402
from _views import VIEW  # noqa: E402
from torchsim.render import Camera, Scene, render  # noqa: E402


def median_time(fn, repeats):
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def mujoco_frames_per_second(model, poses, eye, target, args) -> float:
    """mujoco.Renderer's frames/s on ``--mujoco-frames`` poses, one frame at a time, from a free camera at the same
    pose as ``Camera.look_at(eye, target)`` (lookat, distance, azimuth, elevation)."""
    renderer = mujoco.Renderer(model, args.size, args.size)
    if not args.rgb:
        renderer.enable_depth_rendering()
    free = mujoco.MjvCamera()
    offset = np.subtract(eye, target)
    free.lookat[:] = target
    free.distance = float(np.linalg.norm(offset))
    free.azimuth = float(np.degrees(np.arctan2(offset[1], offset[0]))) + 180.0
    free.elevation = -float(np.degrees(np.arcsin(offset[2] / np.linalg.norm(offset))))
    datas = []
    for q in poses(args.mujoco_frames).cpu().double().numpy():
        d = mujoco.MjData(model)
        d.qpos[:] = q
        mujoco.mj_forward(model, d)
        datas.append(d)

    def frames():
        for d in datas:
            renderer.update_scene(d, free)
            renderer.render()

    return len(datas) / median_time(frames, max(1, args.repeats // 2))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="ant", choices=sorted(VIEW))
    parser.add_argument("--size", type=int, default=64, help="image height = width")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 16, 64, 256, 1024])
    parser.add_argument("--rgb", action="store_true", help="also render Lambert-shaded RGB (MuJoCo: RGB frames)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--mujoco-frames", type=int, default=200)
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--compile", action="store_true", help="render(compile=True): hit tests via torch.compile")
    parser.add_argument("--max-tests", type=int, default=None, help="render(max_tests=...): envs per chunk")
    parser.add_argument("--tile", type=int, default=8, help="render(tile=...): 0 for the dense path")
    parser.add_argument("--no-mujoco", action="store_true", help="torchsim only (no x MuJoCo column)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    xml = torchsim.envs.asset_path(f"{args.env}.xml").read_text()
    eye, target = VIEW[args.env]
    model = mujoco.MjModel.from_xml_string(xml)
    system = torchsim.load_mjcf(xml, device=args.device)
    scene = Scene.build(model, system)
    camera = Camera.look_at(eye, target, fovy=float(model.vis.global_.fovy))
    size, rng = args.size, np.random.default_rng(0)

    def poses(n):
        q = np.tile(model.qpos0, (n, 1))
        hinge = model.jnt_type == mujoco.mjtJoint.mjJNT_HINGE
        q[:, model.jnt_qposadr[hinge]] += rng.uniform(-0.5, 0.5, (n, int(hinge.sum())))
        return torch.as_tensor(q, dtype=system.dtype, device=args.device)

    mj_fps = None if args.no_mujoco else mujoco_frames_per_second(model, poses, eye, target, args)
    kind = "RGB" if args.rgb else "depth"
    print(f"{args.env}, {size}x{size} {kind}, torch threads {torch.get_num_threads()}, device {args.device}, "
          f"compile={args.compile}, tile={args.tile}, max_tests={args.max_tests}, "
          f"MUJOCO_GL={os.environ.get('MUJOCO_GL')}")
    if mj_fps:
        print(f"mujoco.Renderer: {mj_fps:.0f} frames/s (one frame at a time, {args.mujoco_frames} poses)")
    print("| batch | torchsim ms/batch | torchsim frames/s | x MuJoCo |")
    print("|---:|---:|---:|---:|")
    for batch in args.batches:
        q = poses(batch)
        state = torchsim.init(system, q, torch.zeros(batch, system.nv, dtype=system.dtype, device=args.device))

        def ours():
            render(scene, state, camera, size, size, segmentation=False, rgb=args.rgb, compile=args.compile,
                   max_tests=args.max_tests, tile=args.tile)
            if args.device != "cpu":
                torch.cuda.synchronize()

        if args.compile:
            ours()  # the first call per shape type compiles
        seconds = median_time(ours, args.repeats)
        ratio = f"{batch / seconds / mj_fps:.1f}" if mj_fps else "-"
        print(f"| {batch} | {seconds * 1e3:.2f} | {batch / seconds:.0f} | {ratio} |")


if __name__ == "__main__":
    main()
