"""Headless videos of torchsim trajectories, drawn by MuJoCo's renderer from our generalized coordinates.

MuJoCo needs an off-screen OpenGL context: set ``MUJOCO_GL=egl`` (or ``osmesa``) before ``mujoco`` is first
imported; ``scripts/record_video.py`` does so.
"""

import pathlib

import mujoco
import numpy as np
from PIL import Image


def render_frames(model: mujoco.MjModel, qpos: np.ndarray, width: int = 480, height: int = 360,
                  distance: float | None = None, track_body: int = 1) -> list[np.ndarray]:
    """RGB frames ``(height, width, 3)`` of ``model`` at each row of ``qpos (T, nq)``, the camera tracking
    ``track_body`` (default: the first body after the world)."""
    qpos = np.asarray(qpos, dtype=np.float64)
    if qpos.ndim != 2 or qpos.shape[1] != model.nq:
        raise ValueError(f"qpos must have shape (T, {model.nq}), got {qpos.shape}")
    data = mujoco.MjData(model)
    track_body = min(track_body, model.nbody - 1)
    camera = mujoco.MjvCamera()  # a free camera re-aimed at the tracked body every frame
    camera.distance = distance or _framing_distance(model, data, track_body)
    camera.elevation, camera.azimuth = -20.0, 90.0
    try:
        renderer = mujoco.Renderer(model, height, width)
    except Exception as err:  # no GL context: say how to get one
        raise RuntimeError(f"MuJoCo could not open an off-screen GL context ({err}); set MUJOCO_GL=egl or "
                           "MUJOCO_GL=osmesa before importing mujoco") from err
    frames = []
    with renderer:
        for row in qpos:
            data.qpos[:] = row
            mujoco.mj_kinematics(model, data)
            camera.lookat[:] = data.xpos[track_body]
            renderer.update_scene(data, camera)
            frames.append(renderer.render().copy())
    return frames


def _framing_distance(model: mujoco.MjModel, data: mujoco.MjData, body: int) -> float:
    """Camera distance that frames the model's moving bodies at ``qpos0`` (the floor plane would dominate
    ``model.stat.extent``)."""
    mujoco.mj_kinematics(model, data)
    spread = np.linalg.norm(data.xpos[1:] - data.xpos[body], axis=-1).max(initial=0.0)
    return max(1.0, 4.0 * (spread + 0.2))


def save_gif(frames: list[np.ndarray], path, fps: float) -> pathlib.Path:
    """Write ``frames`` as an animated GIF at ``fps`` frames per second (Pillow; no ffmpeg needed)."""
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    images = [Image.fromarray(f) for f in frames]
    images[0].save(path, save_all=True, append_images=images[1:], duration=int(round(1000 / fps)), loop=0)
    return path
