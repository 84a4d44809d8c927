"""Pinhole cameras: where each env's cameras are, and the rays through their pixels.

A camera follows MuJoCo's convention: it looks along its frame's ``-z`` axis with ``+y`` up and ``+x`` to the right
of the image, and ``fovy`` [degrees] is the vertical field of view; the horizontal one follows from the image's
aspect ratio. Pixel ``(i, j)`` (row ``i`` from the top) is sampled through its centre, so the ray in the camera
frame is ``(X[j], Y[i], -1)`` with ``X[j] = (2 (j + 1/2) / W - 1) tan(fovy / 2) W / H`` and
``Y[i] = (1 - 2 (i + 1/2) / H) tan(fovy / 2)``. Its ``-z`` component being 1, the ray parameter ``t`` of a hit is
the hit's planar z-depth, which is what depth images hold (as MuJoCo's depth buffer).

Cameras come from the MJCF (``<camera>`` with ``mode="fixed"``, attached to any body, or ``mode="track"``: carried
by a body's position with a fixed world orientation) or are made in code (:meth:`Camera.look_at`,
:meth:`Camera.on_body`). A :class:`Camera` holds ``C`` cameras; they are posed per env from the body frames.
"""

from typing import NamedTuple

import mujoco
import numpy as np
import torch

from torchsim.render.frames import quat_to_mat_np


class Camera(NamedTuple):
    """``C`` cameras, each fixed on a torchsim body (or the world).

    World pose per env: position ``x_body + R_body anchor + offset``; orientation ``R_body rot``, or ``rot`` alone
    where ``track`` (MuJoCo's ``mode="track"``: the camera moves with the body but does not turn with it).

    Attributes:
        body: (C,) ext index of the carrying torchsim body (``-1``: the world).
        anchor: (C, 3) point on the body, body frame (the body COM frame of ``State.x_pos``/``x_quat``).
        offset: (C, 3) world-frame offset added to the anchor (track cameras; zero otherwise).
        rot: (C, 3, 3) camera axes (columns x, y, z) in the body frame (world frame where ``track``).
        track: (C,) bool.  fovy: (C,) vertical field of view [degrees].  names: (C,) names.
    """

    body: torch.Tensor
    anchor: torch.Tensor
    offset: torch.Tensor
    rot: torch.Tensor
    track: torch.Tensor
    fovy: torch.Tensor
    names: tuple

    @property
    def num(self) -> int:
        return len(self.names)

    @staticmethod
    def look_at(eye, target, up=(0.0, 0.0, 1.0), fovy: float = 45.0, name: str = "look_at") -> "Camera":
        """A world-fixed camera at ``eye`` looking at ``target``, ``up`` as close to the image's up as possible."""
        eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
        z = eye - target
        z = z / np.linalg.norm(z)
        x = np.cross(up, z)
        if np.linalg.norm(x) < 1e-9:
            raise ValueError("look_at: the viewing direction is parallel to `up`")
        x = x / np.linalg.norm(x)
        return _camera([-1], [eye], [np.zeros(3)], [np.stack((x, np.cross(z, x), z), 1)], [False], [fovy], [name])

    @staticmethod
    def on_body(scene, body, pos=(0.0, 0.0, 0.0), quat=(1.0, 0.0, 0.0, 0.0), fovy: float = 45.0,
                name: str = "on_body") -> "Camera":
        """A camera fixed on MuJoCo body ``body`` (name or id) of ``scene``, at ``pos``/``quat`` in that body's
        frame (as a ``<camera>`` element inside the ``<body>``)."""
        b = scene.mjbody_names.index(body) if isinstance(body, str) else int(body)
        mrot = scene.mjbody_rot[b].double().cpu().numpy()
        anchor = scene.mjbody_pos[b].double().cpu().numpy() + mrot @ np.asarray(pos, dtype=np.float64)
        return _camera([int(scene.mjbody_body[b])], [anchor], [np.zeros(3)], [mrot @ quat_to_mat_np(quat)],
                       [False], [fovy], [name])

    @staticmethod
    def cat(cameras) -> "Camera":
        """The cameras of a list of :class:`Camera`, in order."""
        cameras = list(cameras)
        return Camera(*(torch.cat([c[i] for c in cameras]) for i in range(6)),
                      tuple(n for c in cameras for n in c.names))

    def select(self, index) -> "Camera":
        index = torch.as_tensor(index, dtype=torch.long)
        return Camera(*(x[index] for x in self[:6]), tuple(self.names[i] for i in index.tolist()))

    def to(self, device=None, dtype=None) -> "Camera":
        return Camera(*(x.to(device=device, dtype=dtype if x.is_floating_point() else None) for x in self[:6]),
                      self.names)

    def poses(self, pos: torch.Tensor, rot: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """World positions ``(B, C, 3)`` and axes ``(B, C, 3, 3)`` from the body frames of
        :func:`torchsim.render.frames.body_frames` (``(B, N + 1, 3)``, ``(B, N + 1, 3, 3)``)."""
        bpos, brot = pos[:, self.body], rot[:, self.body]
        where = bpos + (brot @ self.anchor.unsqueeze(-1)).squeeze(-1) + self.offset
        axes = torch.where(self.track[:, None, None], self.rot, brot @ self.rot)
        return where, axes


def pixel_rays(fovy: torch.Tensor, height: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Ray slopes of every pixel centre: ``X (C, W)`` and ``Y (C, H)``; pixel ``(i, j)``'s ray in the camera
    frame is ``(X[j], Y[i], -1)`` (see the module docstring)."""
    half = torch.tan(torch.deg2rad(fovy) / 2)[:, None]
    j = torch.arange(width, dtype=fovy.dtype, device=fovy.device)
    i = torch.arange(height, dtype=fovy.dtype, device=fovy.device)
    x = (2 * (j + 0.5) / width - 1) * half * (width / height)
    y = (1 - 2 * (i + 0.5) / height) * half
    return x, y


def cameras_from_model(m: mujoco.MjModel, mj_body, mj_pos, mj_rot) -> tuple[Camera, tuple]:
    """The model's drawable cameras, and ``(name, reason)`` for the ones left out (other modes, orthographic or
    sensor-intrinsics cameras), given each MuJoCo body's torchsim body ``mj_body`` and frame ``mj_pos, mj_rot``
    in it."""
    rows, refused = [], []
    for c in range(m.ncam):
        name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_CAMERA, c) or f"camera{c}"
        mode, b = int(m.cam_mode[c]), int(m.cam_bodyid[c])
        if int(m.cam_projection[c]) != int(mujoco.mjtProjection.mjPROJ_PERSPECTIVE):
            refused.append((name, "orthographic cameras are not supported"))
        elif np.any(m.cam_sensorsize[c] > 0):
            refused.append((name, "cameras given by sensor intrinsics (sensorsize/focal) are not supported"))
        elif mode == int(mujoco.mjtCamLight.mjCAMLIGHT_FIXED):
            rows.append((mj_body[b], mj_pos[b] + mj_rot[b] @ m.cam_pos[c], np.zeros(3),
                         mj_rot[b] @ quat_to_mat_np(m.cam_quat[c]), False, m.cam_fovy[c], name))
        elif mode == int(mujoco.mjtCamLight.mjCAMLIGHT_TRACK):
            rows.append((mj_body[b], mj_pos[b], m.cam_pos0[c].astype(np.float64),
                         m.cam_mat0[c].reshape(3, 3).astype(np.float64), True, m.cam_fovy[c], name))
        else:
            refused.append((name, f"camera mode {mujoco.mjtCamLight(mode).name} is not supported (fixed, track)"))
    return _camera(*zip(*rows)) if rows else _camera(*[[]] * 7), tuple(refused)


def _camera(body, anchor, offset, rot, track, fovy, names) -> Camera:
    f64 = lambda v, shape: torch.as_tensor(np.array(v, dtype=np.float64).reshape(shape))
    return Camera(torch.as_tensor(np.array(body, dtype=np.int64).reshape(-1)), f64(anchor, (-1, 3)),
                  f64(offset, (-1, 3)), f64(rot, (-1, 3, 3)), torch.as_tensor(np.array(track, dtype=bool).reshape(-1)),
                  f64(fovy, (-1,)), tuple(names))


__all__ = ["Camera", "pixel_rays", "cameras_from_model"]
