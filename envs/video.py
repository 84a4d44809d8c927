"""Headless videos of torchsim trajectories, from our generalized coordinates ``q`` (a ``(T, nq)`` trajectory).

Two renderers draw the frames:

- :func:`render_frames_torchsim` (the default): torchsim's own ray caster (:mod:`torchsim.render`), all frames of
  the trajectory as one batch, lambert shading, in this process, no OpenGL context (works on any headless
  machine); any camera: the model's ``<camera>`` elements (fixed or track), :meth:`Camera.look_at`, or by default
  a camera tracking a body as the MuJoCo path does. Meshes, textures and shadows are not drawn
  (``docs/rendering.md``).
- :func:`render_frames`: MuJoCo's renderer. It needs an off-screen OpenGL context: set ``MUJOCO_GL=egl`` (or
  ``osmesa``) before ``mujoco`` is first imported; ``scripts/record_video.py --renderer mujoco`` does so, and
  training runs fall back to it (in a child process) for models torchsim's renderer cannot draw.

:func:`save_video` writes MP4 where ``imageio`` with ``imageio-ffmpeg`` is installed, else an animated GIF.
"""

import pathlib
import warnings

import mujoco
import numpy as np
import torch
from PIL import Image

#: Background colour of torchsim-rendered videos (a light grey-blue sky).
BACKGROUND = (0.62, 0.70, 0.80)


def render_frames(model: mujoco.MjModel, qpos: np.ndarray, width: int = 480, height: int = 360,
                  distance: float | None = None, track_body: int = 1, camera=None) -> list[np.ndarray]:
    """RGB frames ``(height, width, 3)`` of ``model`` at each row of ``qpos (T, nq)`` drawn by MuJoCo's renderer,
    the camera tracking ``track_body`` (default: the first body after the world), or the model camera ``camera``
    (name or index)."""
    qpos = np.asarray(qpos, dtype=np.float64)
    if qpos.ndim != 2 or qpos.shape[1] != model.nq:
        raise ValueError(f"qpos must have shape (T, {model.nq}), got {qpos.shape}")
    data = mujoco.MjData(model)
    track_body = min(track_body, model.nbody - 1)
    model_camera, camera = camera, mujoco.MjvCamera()  # a free camera re-aimed at the tracked body every frame
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
            renderer.update_scene(data, camera if model_camera is None else model_camera)
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


def tracking_camera(scene, model: mujoco.MjModel, distance: float, track_body: int = 1, elevation: float = -20.0,
                    azimuth: float = 90.0, fovy: float | None = None):
    """A :class:`torchsim.render.Camera` that follows MuJoCo body ``track_body``'s origin at ``distance`` without
    turning (MuJoCo's ``mode="track"``), looking along ``azimuth``/``elevation`` [degrees] as MuJoCo's free camera
    (``azimuth=90``: from the ``-y`` side); ``fovy`` defaults to the model's ``vis.global_.fovy``."""
    from torchsim.render import Camera

    az, el = np.deg2rad(azimuth), np.deg2rad(elevation)
    forward = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    offset = -distance * forward
    fovy = float(model.vis.global_.fovy) if fovy is None else float(fovy)
    look = Camera.look_at(eye=offset, target=(0.0, 0.0, 0.0), fovy=fovy, name=f"track_{track_body}")
    b = min(int(track_body), model.nbody - 1)
    return look._replace(body=scene.mjbody_body[b:b + 1].clone(), anchor=scene.mjbody_pos[b:b + 1].clone(),
                         offset=torch.as_tensor(offset[None]), track=torch.tensor([True]))


def render_frames_torchsim(model: mujoco.MjModel, system, qpos: np.ndarray, width: int = 320, height: int = 240,
                           camera=None, distance: float | None = None, track_body: int = 1, batch: int = 64,
                           background=BACKGROUND, scene=None, compile: bool = False,
                           checker: float | None = None, endless_floor: bool = True) -> list[np.ndarray]:
    """RGB frames ``(height, width, 3)`` uint8 of ``qpos (T, nq)`` drawn by torchsim's renderer.

    Args:
        model, system: the env's ``mj_model`` and ``sys`` (``Scene.build(model, system)``; pass ``scene`` to reuse
            one).
        camera: a model camera's name or index, a :class:`torchsim.render.Camera`, or None: a camera tracking
            ``track_body`` from ``distance`` (default: framing the bodies, as :func:`render_frames`).
        batch: frames ray cast per call (memory: ~0.1 GB per 64 frames at 320x240 for the ant).
        checker: side [m] of the checkerboard squares darkened on planes (the renderer draws no textures; without
            them a tracked body on a plain floor seems not to move); default a quarter of the framing distance,
            0 for none.
        endless_floor: draw the world's planes infinite (a running body leaves a finite floor within seconds).
        compile: ``torch.compile`` the hit tests (:func:`torchsim.render.render`; a few seconds of compilation per
            shape type on first use in a machine, cached on disk by inductor).

    Raises :class:`torchsim.render.UnsupportedGeomError` for models with SDF geoms (meshes and height fields are
    drawn).
    """
    from torchsim.render import Scene, render
    from torchsim.render.viewer import trajectory

    qpos = np.asarray(qpos, dtype=np.float64)
    if qpos.ndim != 2 or qpos.shape[1] != model.nq:
        raise ValueError(f"qpos must have shape (T, {model.nq}), got {qpos.shape}")
    scene = Scene.build(model, system) if scene is None else scene
    if endless_floor:
        scene = _endless_floor(scene)
    distance = distance or _framing_distance(model, mujoco.MjData(model), min(track_body, model.nbody - 1))
    if camera is None:
        camera = tracking_camera(scene, model, distance, track_body)
    checker = 0.25 * distance if checker is None else float(checker)
    x_pos, x_quat = trajectory(system, qpos)
    frames = []
    with torch.no_grad():
        for start in range(0, len(x_pos), batch):
            part = (x_pos[start:start + batch], x_quat[start:start + batch])
            images = render(scene, part, camera, height, width, segmentation=checker > 0, rgb=True,
                            background_rgb=background, compile=compile)
            rgb = images.rgb if images.rgb.ndim == 4 else images.rgb[:, 0]
            if checker > 0:
                rgb = _checkerboard(scene, camera, part, images, rgb, checker)
            frames.extend((rgb.clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy())
    return frames


def _endless_floor(scene):
    """``scene`` with its world-fixed planes made infinite (MuJoCo size 0)."""
    import dataclasses

    floor = torch.tensor([kind == "plane" for kind in scene.geom_type], dtype=torch.bool)
    floor &= scene.geom_body.cpu() == scene.num_bodies
    if not floor.any():
        return scene
    size, radius = scene.geom_size.clone(), scene.geom_radius.clone()
    size[floor.to(size.device), :2] = 0.0
    radius[floor.to(radius.device)] = float("inf")
    return dataclasses.replace(scene, geom_size=size, geom_radius=radius)


def _checkerboard(scene, camera, poses, images, rgb, square: float, dark: float = 0.8):
    """``rgb (B, H, W, 3)`` with alternate ``square``-metre squares (in world ``x, y``) of every plane geom
    darkened by ``dark``: each plane pixel's world point from its depth and the camera's pose."""
    from torchsim.render.camera import pixel_rays
    from torchsim.render.frames import body_frames

    planes = scene.geom_id[[i for i, kind in enumerate(scene.geom_type) if kind == "plane"]]
    cams = scene.camera(camera).select([0]).to(rgb.device, poses[0].dtype)
    seg, depth = (x if x.ndim == 3 else x[:, 0] for x in (images.segmentation, images.depth))
    cam_pos, cam_rot = cams.poses(*body_frames(*poses))  # (B, 1, 3), (B, 1, 3, 3)
    xs, ys = pixel_rays(cams.fovy, *depth.shape[1:])
    ray = torch.stack(torch.broadcast_tensors(xs[0][None, :], ys[0][:, None], -torch.ones_like(ys[0])[:, None]), -1)
    world = cam_pos[:, 0, None, None] + depth[..., None] * torch.einsum("bij,hwj->bhwi", cam_rot[:, 0], ray)
    cell = torch.floor(world[..., 0] / square) + torch.floor(world[..., 1] / square)
    shade = torch.where(torch.isin(seg, planes) & (cell.remainder(2) == 1), dark, 1.0)
    return rgb * shade[..., None].to(rgb.dtype)


def save_video(frames: list[np.ndarray], path, fps: float) -> pathlib.Path:
    """Write ``frames`` to ``path``: MP4 (H.264) where the suffix is ``.mp4`` and ``imageio`` with
    ``imageio-ffmpeg`` is installed, else an animated GIF (``path`` with suffix ``.gif``, with a warning where an
    MP4 was asked for). Returns the path written."""
    path = pathlib.Path(path)
    if path.suffix.lower() == ".mp4":
        import importlib.util

        if importlib.util.find_spec("imageio") is None or importlib.util.find_spec("imageio_ffmpeg") is None:
            warnings.warn("MP4 needs imageio and imageio-ffmpeg (pip install 'torchsim[video]'); writing a GIF")
            return save_gif(frames, path.with_suffix(".gif"), fps)
        import imageio.v2 as imageio

        path.parent.mkdir(parents=True, exist_ok=True)
        # yuv420p needs even sides: pad the last row/column where odd
        frames = [np.pad(f, ((0, f.shape[0] % 2), (0, f.shape[1] % 2), (0, 0)), mode="edge") for f in frames]
        imageio.mimwrite(path, frames, fps=fps, codec="libx264", quality=7, macro_block_size=1,
                         pixelformat="yuv420p")
        return path
    return save_gif(frames, path, fps)
