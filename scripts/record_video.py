"""Record one env's episode, under a random policy or a trained one, as a GIF or MP4.

    python scripts/record_video.py --env ant --steps 200 --out docs/media/ant_random.gif
    python scripts/record_video.py --policy outputs/ppo_ant/<run>/checkpoints/last.pt --renderer torchsim \
        --out docs/media/ant_trained_torchsim.gif
    python scripts/record_video.py --env reacher --camera 0,-1,1.2,0,0,0      # a look-at camera: eye, target
    python scripts/record_video.py --env ant --bench                           # frames/s of both renderers

The physics runs in torchsim (one env, float32, eager); the renderer draws the recorded ``state.q`` trajectory,
one frame per env step (``dt`` apart), so the video plays in real time. ``--renderer torchsim``: torchsim's ray
caster, no OpenGL context; ``--renderer mujoco``: MuJoCo's renderer through EGL (``MUJOCO_GL``); ``auto``
(default): MuJoCo where it opens a GL context (in this process it draws frames faster at 320x240 and up: see
``--bench`` and docs/rendering.md), else torchsim. A training run's ``policy.gif`` uses torchsim's renderer: it
skips the child process MuJoCo needs there, which makes it faster end to end.
``--camera``: ``track`` (default: follows the first body), a model camera's name or index, or ``x,y,z,tx,ty,tz``
(eye and target of a world-fixed camera; torchsim renderer only). An ``.mp4`` path needs ``imageio`` and
``imageio-ffmpeg`` (``pip install 'torchsim[video]'``), else a GIF is written next to it.
"""

import argparse
import os
import subprocess
import sys
import tempfile
import time

os.environ.setdefault("MUJOCO_GL", "egl")  # before mujoco is imported (by torchsim)

import numpy as np  # noqa: E402
import torch  # noqa: E402

import torchsim.envs  # noqa: E402
from torchsim.envs.video import render_frames, render_frames_torchsim, save_video  # noqa: E402


def parse_camera(text: str, fovy: float):
    """``track`` -> None, an integer -> a model camera index, six comma-separated numbers -> a look-at camera,
    anything else -> a model camera name."""
    from torchsim.render import Camera

    if text == "track":
        return None
    if text.lstrip("-").isdigit():
        return int(text)
    parts = text.split(",")
    if len(parts) == 6:
        values = [float(v) for v in parts]
        return Camera.look_at(eye=values[:3], target=values[3:], fovy=fovy)
    return text


def random_rollout(env_name: str, steps: int):
    """``(qpos (T, nq), dt, return, env)`` of one episode under uniformly random actions."""
    env = torchsim.envs.make(env_name, num_envs=1)
    td = env.reset()
    qpos, total, start = [env.state.q[0].double().numpy()], 0.0, time.perf_counter()
    for i in range(steps):
        td["action"] = env.action_spec.rand()
        td = env.step(td)
        total += td["next", "reward"].item()
        qpos.append(env.state.q[0].double().numpy())
        if (i + 1) % 50 == 0:
            rate = (i + 1) / (time.perf_counter() - start)
            print(f"step {i + 1}/{steps}  return {total:.2f}  {rate:.1f} env-steps/s", flush=True)
        if td["next", "done"].item():
            print(f"episode ended at step {i + 1}")
            break
        td = env.step_mdp(td)
    return np.stack(qpos), env.dt, total, env


def policy_rollout(checkpoint: str, steps: int | None):
    """``(qpos, dt, return, base env, env name)`` of one deterministic episode of a trained policy."""
    from omegaconf import OmegaConf

    from torchsim.algos.checkpoints import load_checkpoint, load_policy
    from torchsim.algos.env_factory import make_env
    from torchsim.algos.evaluation import evaluate

    ckpt = load_checkpoint(checkpoint)
    cfg = OmegaConf.create(ckpt["cfg"])
    env = make_env(cfg, 1, "cpu")
    actor = load_policy(ckpt, env, "cpu")
    ev = evaluate(env, actor, steps or cfg.eval.max_steps, record=True)
    return ev.trajectory, env.base_env.dt, ev.ret.item(), env.base_env, cfg.env.name


def bench(env, env_name: str, qpos: np.ndarray, dt: float, width: int, height: int, compile: bool = False) -> None:
    """Frames/s of each renderer on the same trajectory: the frames alone (in this process; also per CPU-second of
    the process, all threads: MuJoCo's EGL is Mesa llvmpipe, multi-threaded), and end to end as a training run's
    ``policy.gif`` (``render_gif``: torchsim's in-process path vs MuJoCo's child process)."""
    from torchsim.algos.physics_task import render_gif

    n = len(qpos)
    draw_torchsim = lambda: render_frames_torchsim(env.mj_model, env.sys, qpos, width, height, compile=compile)
    draw_mujoco = lambda: render_frames(env.mj_model, qpos, width, height)
    for name, draw in (("torchsim", draw_torchsim), ("mujoco", draw_mujoco)):
        draw()  # warm-up
        start, cpu = time.perf_counter(), time.process_time()
        draw()
        wall, cpu = time.perf_counter() - start, time.process_time() - cpu
        print(f"{name:9s} frames only, {width}x{height}, {n} frames: {n / wall:6.1f} frames/s, "
              f"{n / cpu:6.1f} frames per CPU-second")
    with tempfile.TemporaryDirectory() as tmp:
        for renderer in ("torchsim", "mujoco"):
            start = time.perf_counter()
            if renderer == "torchsim":
                render_gif(env_name, qpos, dt, os.path.join(tmp, "t.gif"), renderer="torchsim", width=width,
                           height=height)
            else:  # the child process, as a training run starts it (torchsim.algos.render: its own resolution)
                np.save(os.path.join(tmp, "q.npy"), qpos)
                subprocess.run([sys.executable, "-m", "torchsim.algos.render", env_name, os.path.join(tmp, "q.npy"),
                                os.path.join(tmp, "m.gif"), str(1.0 / dt), str(width), str(height)], check=True,
                               env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})
            wall = time.perf_counter() - start
            print(f"{renderer:9s} policy.gif end to end, {width}x{height}, {n} frames: {wall:5.2f} s = "
                  f"{n / wall:6.1f} frames/s")


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env", default="ant", choices=torchsim.envs.list("physics"))
    p.add_argument("--policy", default=None, help="a training run's checkpoints/last.pt (default: random actions)")
    p.add_argument("--steps", type=int, default=None, help="env steps (default 200 random, or the episode length)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help=".gif or .mp4 path (default docs/media/<env>_random.gif)")
    p.add_argument("--renderer", default="auto", choices=("auto", "torchsim", "mujoco"))
    p.add_argument("--camera", default="track", help="track | model camera name or index | x,y,z,tx,ty,tz")
    p.add_argument("--fovy", type=float, default=45.0, help="vertical field of view of a look-at camera [deg]")
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--compile", action="store_true", help="torch.compile the torchsim renderer's hit tests")
    p.add_argument("--bench", action="store_true", help="time both renderers on the episode; write no video")
    args = p.parse_args()
    torch.manual_seed(args.seed)
    if args.policy:
        qpos, dt, total, env, env_name = policy_rollout(args.policy, args.steps)
    else:
        qpos, dt, total, env = random_rollout(args.env, args.steps or 200)
        env_name = args.env
    if args.bench:
        return bench(env, env_name, qpos, dt, args.width, args.height, args.compile)
    camera = parse_camera(args.camera, args.fovy)
    renderer = args.renderer
    if renderer == "auto":  # MuJoCo draws only its own cameras and needs a GL context
        renderer = "mujoco" if camera is None or isinstance(camera, (int, str)) else "torchsim"
    start, frames = time.perf_counter(), None
    if renderer == "mujoco":
        if camera is not None and not isinstance(camera, (int, str)):
            raise SystemExit("--renderer mujoco draws the tracking camera or a model camera (name or index)")
        try:
            frames = render_frames(env.mj_model, qpos, args.width, args.height, camera=camera)
        except RuntimeError as err:
            if args.renderer == "mujoco":
                raise
            print(f"MuJoCo's renderer is unavailable ({err}); using torchsim's")
            renderer = "torchsim"
    if frames is None:
        frames = render_frames_torchsim(env.mj_model, env.sys, qpos, args.width, args.height, camera=camera,
                                        compile=args.compile)
    rate = len(frames) / (time.perf_counter() - start)
    out = args.out or f"docs/media/{env_name}_{'trained' if args.policy else 'random'}.gif"
    path = save_video(frames, out, fps=1.0 / dt)
    print(f"wrote {path} ({len(frames)} frames, {renderer} renderer {rate:.1f} frames/s, return {total:.2f})")


if __name__ == "__main__":
    main()
