"""Record one env's episode under a random policy as an animated GIF.

    python scripts/record_video.py --env ant --steps 200 --out docs/media/ant_random.gif

The physics runs in torchsim (one env, float32, eager); MuJoCo's renderer only draws the poses: ``state.q`` is
written into ``MjData.qpos`` each env step (``dt`` apart), so the GIF plays in real time.
"""

import argparse
import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")  # before mujoco is imported (by torchsim)

import torch  # noqa: E402

import torchsim.envs  # noqa: E402
from torchsim.envs.video import render_frames, save_gif  # noqa: E402


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env", default="ant", choices=torchsim.envs.list())
    p.add_argument("--steps", type=int, default=200, help="env steps to record (stops early if the episode ends)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="GIF path (default docs/media/<env>_random.gif)")
    p.add_argument("--width", type=int, default=480)
    p.add_argument("--height", type=int, default=360)
    args = p.parse_args()
    torch.manual_seed(args.seed)
    env = torchsim.envs.make(args.env, num_envs=1)
    td = env.reset()
    qpos, total, start = [env.state.q[0].double().numpy()], 0.0, time.perf_counter()
    for i in range(args.steps):
        td["action"] = env.action_spec.rand()
        td = env.step(td)
        total += td["next", "reward"].item()
        qpos.append(env.state.q[0].double().numpy())
        if (i + 1) % 20 == 0:
            rate = (i + 1) / (time.perf_counter() - start)
            print(f"step {i + 1}/{args.steps}  return {total:.2f}  {rate:.1f} env-steps/s", flush=True)
        if td["next", "done"].item():
            print(f"episode ended at step {i + 1}")
            break
        td = env.step_mdp(td)
    out = args.out or f"docs/media/{args.env}_random.gif"
    path = save_gif(render_frames(env.mj_model, qpos, args.width, args.height), out, fps=1.0 / env.dt)
    print(f"wrote {path} ({len(qpos)} frames, return {total:.2f})")


if __name__ == "__main__":
    main()
