"""Render a saved ``q`` trajectory as a GIF with MuJoCo's renderer:
``python -m torchsim.algos.render ENV QPOS.npy OUT.gif FPS [WIDTH HEIGHT]`` (default 480x360).

A separate process because MuJoCo chooses its GL backend at import (set ``MUJOCO_GL=egl`` for headless machines);
:func:`torchsim.algos.physics_task.render_gif` runs it for models torchsim's own renderer cannot draw (meshes), or when
asked to (``renderer="mujoco"``).
"""

import os
import sys

os.environ.setdefault("MUJOCO_GL", "egl")  # before mujoco is imported (by torchsim)

import numpy as np  # noqa: E402

import torchsim.envs  # noqa: E402
from torchsim.envs.video import render_frames, save_gif  # noqa: E402

if __name__ == "__main__":
    env_name, qpos_path, out, fps = sys.argv[1:5]
    width, height = (int(v) for v in sys.argv[5:7]) if len(sys.argv) >= 7 else (480, 360)
    # the env's own MuJoCo model: for a URDF task it is the translated model with the env's floor and light
    mj_model = torchsim.envs.make(env_name).mj_model
    save_gif(render_frames(mj_model, np.load(qpos_path), width, height), out, fps=float(fps))
