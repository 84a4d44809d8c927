"""Interactive 3D viewer in the browser, built on `viser <https://viser.studio>`_ (three.js client, Python server).

    from torchsim.render import Scene
    from torchsim.render.viewer import Viewer, save_html
    scene = Scene.build(env.mj_model, env.sys)
    viewer = Viewer(scene)                 # prints the URL (http://127.0.0.1:8080); open it in a browser
    viewer.update(env.state)               # pose the bodies as in env 0 of the state (call it every step)
    save_html(scene, (x_pos, x_quat), "rollout.html", dt=env.dt)   # one self-contained file (~1 MB + poses)

Each geom of the :class:`~torchsim.render.Scene` (plane, sphere, capsule, ellipsoid, cylinder, box, mesh geoms
with their own triangles, height fields as the scene triangulates them) becomes a mesh in its colour, a child of
its torchsim body's frame; per update only the bodies' frames move (``State.x_pos`` / ``x_quat``, as
:func:`torchsim.render.render` reads them). A mocap body's geoms are children of a frame at its model pose
(``Scene.mocap_pos``/``mocap_quat``) until an update, or a trajectory's ``mocap`` poses, give theirs.
:func:`save_html` records a trajectory into a single HTML file holding viser's client and the recording
(playback bar, orbit camera) that opens in a browser from disk, with neither torchsim nor Python installed.
``pip install -e '.[viewer]'`` installs viser; ``scripts/view.py`` opens rollouts, trained policies and live
training runs.

Camera: ``eye``/``target``/``fovy`` (degrees, vertical) set the initial view as :meth:`Camera.look_at` does,
with ``+z`` up; the browser's camera then follows the mouse.
"""

import contextlib
import io
import ipaddress
import pathlib
import warnings

import numpy as np
import torch

#: Half side [m] of the square drawn for an infinite plane (MuJoCo size 0), unless ``plane_extent`` says otherwise.
PLANE_EXTENT = 10.0


def _viser():
    try:
        import viser
    except ImportError as err:
        raise ImportError("the viewer needs viser: pip install viser "
                          "(in a torchsim checkout: pip install -e '.[viewer]')") from err
    return viser


def is_loopback(host: str) -> bool:
    """Whether ``host`` (a name or an address) is this machine's loopback, which no other machine can reach."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # a host name: it may resolve to an address others reach
        return False


def geom_mesh(kind: str, size, plane_extent: float = PLANE_EXTENT) -> tuple[np.ndarray, np.ndarray]:
    """Vertices ``(V, 3)`` and triangles ``(F, 3)`` of a geom in its own frame (MuJoCo's conventions: capsules and
    cylinders along ``z`` with ``size = (radius, half length)``, boxes by half sides, planes in ``xy`` facing
    ``+z``, a 0 plane size meaning infinite, drawn ``plane_extent`` wide)."""
    import trimesh.creation  # a dependency of viser

    size = np.asarray(size, dtype=np.float64)
    if kind == "plane":
        sx, sy = (s if s > 0 else plane_extent for s in size[:2])
        v = np.array([[-sx, -sy, 0.0], [sx, -sy, 0.0], [sx, sy, 0.0], [-sx, sy, 0.0]])
        return v, np.array([[0, 1, 2], [0, 2, 3]])
    if kind in ("sphere", "ellipsoid"):
        mesh = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
        scale = size[:3] if kind == "ellipsoid" else np.full(3, size[0])
        return np.asarray(mesh.vertices) * scale, np.asarray(mesh.faces)
    if kind == "capsule":
        mesh = trimesh.creation.capsule(height=2 * size[1], radius=size[0], count=[24, 24])
    elif kind == "cylinder":
        mesh = trimesh.creation.cylinder(radius=size[0], height=2 * size[1], sections=32)
    elif kind == "box":
        mesh = trimesh.creation.box(extents=2 * size[:3])
    else:
        raise ValueError(f"no mesh for geom type {kind!r}")
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def scene_geom_mesh(scene, k: int, plane_extent: float = PLANE_EXTENT) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of the scene's geom ``k`` in its own frame: a mesh geom's own (MuJoCo's
    ``mesh_vert``/``mesh_face``, in the mesh frame, which is the geom frame), a height field's triangulation
    (surface, walls and bottom, as the renderer draws it: :mod:`torchsim.render.hfield`), else :func:`geom_mesh`."""
    if scene.geom_mesh is not None and int(scene.geom_mesh[k]) >= 0:
        return scene.meshes.geometry(int(scene.geom_mesh[k]))
    return geom_mesh(scene.geom_type[k], scene.geom_size[k].detach().cpu().double().numpy(), plane_extent)


def _wxyz(rot: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(..., 4)`` (``wxyz``) of rotation matrices ``(..., 3, 3)``."""
    from viser.transforms import SO3

    return np.stack([SO3.from_matrix(r).wxyz for r in rot.reshape(-1, 3, 3)]).reshape(*rot.shape[:-2], 4)


def _frame(value, env: int, count: int, width: int, label: str) -> np.ndarray:
    """Env ``env``'s ``(count, width)`` rows of ``value``, given shared ``(count, width)`` or per env
    ``(B, count, width)``."""
    value = torch.as_tensor(value).detach().cpu().double()
    if value.shape[-2:] != (count, width) or value.ndim not in (2, 3):
        raise ValueError(f"{label} must be ({count}, {width}) or (B, {count}, {width}) for this scene's {count} mocap "
                         f"bodies, got {tuple(value.shape)}")
    return (value if value.ndim == 2 else value[env]).numpy()


def mocap_track(mocap, frames: int, count: int) -> tuple[np.ndarray, np.ndarray]:
    """The mocap bodies' positions ``(frames, count, 3)`` and unit quaternions ``(frames, count, 4)`` (float64
    numpy) of a trajectory's ``mocap = (mocap_pos, mocap_quat)``: each given for every frame ``(T, K, .)`` or
    once for all ``(K, .)``; ``None`` gives none, ``(frames, 0, .)``, and the mocap bodies stay where they are."""
    if mocap is None:
        return np.empty((frames, 0, 3)), np.empty((frames, 0, 4))
    track = []
    for value, width, label in zip(mocap, (3, 4), ("mocap_pos", "mocap_quat")):
        value = torch.as_tensor(value).detach().cpu().double()
        value = value.expand(frames, *value.shape) if value.ndim == 2 else value
        if value.shape != (frames, count, width):
            raise ValueError(f"{label} must be ({count}, {width}) or (T, {count}, {width}) for this scene's {count} "
                             f"mocap bodies over the trajectory's T = {frames} frames, got {tuple(value.shape)}")
        track.append(value.numpy())
    return track[0], track[1] / np.linalg.norm(track[1], axis=-1, keepdims=True)


def body_poses(poses, env: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Body positions ``(T, N, 3)`` and quaternions ``(T, N, 4)`` (float64 numpy) from a ``torchsim.State`` (its
    env ``env``: one frame), or from ``(x_pos, x_quat)`` of shapes ``(T, N, 3)``, ``(T, N, 4)`` (a trajectory)
    or ``(N, 3)``, ``(N, 4)`` (one frame)."""
    if hasattr(poses, "x_pos"):
        x_pos, x_quat = poses.x_pos[env:env + 1], poses.x_quat[env:env + 1]
    else:
        x_pos, x_quat = poses
    x_pos, x_quat = (torch.as_tensor(x).detach().cpu().double() for x in (x_pos, x_quat))
    if x_pos.ndim == 2:
        x_pos, x_quat = x_pos[None], x_quat[None]
    return x_pos.numpy(), (x_quat / x_quat.norm(dim=-1, keepdim=True)).numpy()


class Viewer:
    """A viser server showing ``scene``: open its URL in a browser; :meth:`update` poses the bodies.

    Args:
        scene: the model's :class:`torchsim.render.Scene`.
        host, port: where the server listens (the next free port is taken where ``port`` is busy; see ``url``).
            The default, ``127.0.0.1``, serves this machine only; any other host (``0.0.0.0``: every network
            interface) lets anyone who reaches it watch the scene, and the viewer warns so.
        eye, target, fovy: initial camera (world frame, degrees); default: from the ``-y`` side, 20 degrees above,
            looking at the bodies' centre at ``q0``, far enough to frame them.
        plane_extent: half side [m] of the square drawn for infinite planes.
        verbose: let viser print its banner with the URL (and "Server stopped" at :meth:`close`).
    """

    def __init__(self, scene, host: str = "127.0.0.1", port: int = 8080, eye=None, target=None, fovy: float = 45.0,
                 plane_extent: float = PLANE_EXTENT, verbose: bool = True):
        viser = _viser()
        self.scene, self.verbose = scene, verbose
        with self._quiet():
            self.server = viser.ViserServer(host=host, port=port, verbose=verbose)
        if not is_loopback(host):
            warnings.warn(f"the viewer listens on {host}, port {self.server.get_port()}: anyone who can reach this "
                          "machine on the network can watch it (host='127.0.0.1' serves this machine only)",
                          stacklevel=2)
        self.server.scene.set_up_direction("+z")
        if eye is not None:
            self.set_camera(eye, (0.0, 0.0, 0.0) if target is None else target, fovy)
        self.bodies = [self.server.scene.add_frame(f"/body{b}", show_axes=False) for b in range(scene.num_bodies)]
        # mocap bodies' geoms ride on their frames, at the model's mocap poses until an update gives theirs
        self.mocap = [self.server.scene.add_frame(f"/mocap{k}", show_axes=False, position=mpos, wxyz=mquat)
                      for k, (mpos, mquat) in enumerate(zip(scene.mocap_pos.detach().cpu().double().numpy(),
                                                            scene.mocap_quat.detach().cpu().double().numpy()))]
        rgba = scene.geom_rgba.detach().cpu().double().numpy()
        pos = scene.geom_pos.detach().cpu().double().numpy()
        wxyz = _wxyz(scene.geom_rot.detach().cpu().double().numpy())
        for k, (kind, body) in enumerate(zip(scene.geom_type, scene.geom_body.tolist())):
            vertices, faces = scene_geom_mesh(scene, k, plane_extent)
            parent = (f"/body{body}" if body < scene.num_bodies else "/world" if body == scene.num_bodies
                      else f"/mocap{body - scene.num_bodies - 1}")
            colour = tuple(int(c) for c in np.clip(np.round(rgba[k, :3] * 255), 0, 255))
            self.server.scene.add_mesh_simple(
                f"{parent}/geom{int(scene.geom_id[k])}", vertices, faces, color=colour, position=pos[k],
                wxyz=wxyz[k], side="double" if kind in ("plane", "mesh", "hfield") else "front",
                flat_shading=kind in ("box", "plane", "hfield"))

    @property
    def url(self) -> str:
        """The address the server is bound to (an IPv6 address in brackets, as URLs write it)."""
        host = self.server.get_host()
        return f"http://{f'[{host}]' if ':' in host else host}:{self.server.get_port()}"

    def set_camera(self, eye, target, fovy: float = 45.0) -> None:
        """The initial camera (and the one "Reset View" returns to), as :meth:`Camera.look_at`."""
        cam = self.server.initial_camera
        cam.position = tuple(float(v) for v in eye)
        cam.look_at = tuple(float(v) for v in target)
        cam.up = (0.0, 0.0, 1.0)
        cam.fov = float(np.deg2rad(fovy))

    def frame(self, eye=None, fovy: float = 45.0, poses=None) -> None:
        """Aim the initial camera at the bodies' centre (of ``poses``, a State or ``(x_pos, x_quat)``, its first
        frame), from ``eye`` or from the ``-y`` side 20 degrees up, far enough to see every body."""
        x_pos = body_poses(poses)[0][0] if poses is not None else np.zeros((1, 3))
        centre = x_pos.mean(0)
        if eye is None:
            spread = np.linalg.norm(x_pos - centre, axis=-1).max(initial=0.0)
            distance = max(1.0, 4.0 * (spread + 0.2))
            el = np.deg2rad(20.0)
            eye = centre + distance * np.array([0.0, -np.cos(el), np.sin(el)])
        self.set_camera(eye, centre, fovy)

    def update(self, poses, env: int = 0, mocap_pos=None, mocap_quat=None) -> None:
        """Move the bodies to ``poses``: a ``torchsim.State`` (env ``env`` is shown) or ``(x_pos, x_quat)`` of one
        frame ``(N, 3)``, ``(N, 4)``; and the mocap bodies to ``mocap_pos (K, 3)``, ``mocap_quat (K, 4)``, shared,
        or ``(B, K, 3)``, ``(B, K, 4)`` per env (the System's, which the step reads: ``env.sys.mocap_pos``); one
        left out keeps the mocap bodies' last poses."""
        x_pos, x_quat = body_poses(poses, env)
        count = len(self.mocap)
        mocap_pos = (np.array([h.position for h in self.mocap]).reshape(count, 3) if mocap_pos is None
                     else _frame(mocap_pos, env, count, 3, "mocap_pos"))
        mocap_quat = (np.array([h.wxyz for h in self.mocap]).reshape(count, 4) if mocap_quat is None
                      else _frame(mocap_quat, env, count, 4, "mocap_quat"))
        self._show(x_pos[0], x_quat[0], mocap_pos, mocap_quat / np.linalg.norm(mocap_quat, axis=-1, keepdims=True))

    def play(self, poses, dt: float, loop: bool = False, mocap=None) -> None:
        """Show a trajectory ``(x_pos (T, N, 3), x_quat (T, N, 4))`` in real time (``dt`` seconds per frame), the
        mocap bodies at ``mocap = (mocap_pos, mocap_quat)`` (:func:`mocap_track`)."""
        import time

        frames = self._frames(poses, mocap)
        while True:
            start = time.perf_counter()
            for t, frame in enumerate(frames):
                self._show(*frame)
                time.sleep(max(0.0, start + (t + 1) * dt - time.perf_counter()))
            if not loop:
                return
            start = time.perf_counter()

    def to_html(self, poses, dt: float, mocap=None) -> str:
        """One self-contained HTML page (viser's client with the recording inlined) playing ``poses`` (a State:
        one frame; or ``(x_pos, x_quat)``: ``(T, N, ...)`` frames ``dt`` seconds apart, on a loop with a
        playback bar), the mocap bodies at ``mocap = (mocap_pos, mocap_quat)`` (:func:`mocap_track`)."""
        frames = self._frames(poses, mocap)
        self._show(*frames[0])
        serializer = self.server.get_scene_serializer()
        for frame in frames[1:]:
            serializer.insert_sleep(dt)
            self._show(*frame)
        if len(frames) > 1:
            serializer.insert_sleep(dt)
        return serializer.as_html()

    def _frames(self, poses, mocap) -> list:
        """Per frame of a trajectory: body positions and quaternions, mocap positions and quaternions."""
        x_pos, x_quat = body_poses(poses)
        return list(zip(x_pos, x_quat, *mocap_track(mocap, len(x_pos), len(self.mocap))))

    def _show(self, x_pos, x_quat, mocap_pos, mocap_quat) -> None:
        """One frame's poses (numpy, unit quaternions): ``(N, 3)``, ``(N, 4)`` and ``(K, 3)``, ``(K, 4)`` (or
        ``(0, .)``: the mocap bodies stay where they are)."""
        with self.server.atomic():
            for handle, position, wxyz in zip(self.bodies, x_pos, x_quat):
                handle.position, handle.wxyz = position, wxyz
            for handle, position, wxyz in zip(self.mocap, mocap_pos, mocap_quat):
                handle.position, handle.wxyz = position, wxyz

    def _quiet(self):
        """Viser prints its banner whatever ``verbose`` says: swallow stdout unless verbose."""
        return contextlib.nullcontext() if self.verbose else contextlib.redirect_stdout(io.StringIO())

    def close(self) -> None:
        with self._quiet():
            self.server.stop()


def save_html(scene, poses, path, dt: float = 0.05, eye=None, target=None, fovy: float = 45.0,
              plane_extent: float = PLANE_EXTENT, mocap=None) -> pathlib.Path:
    """Write ``poses`` (a ``torchsim.State``'s env 0, or a trajectory ``(x_pos (T, N, 3), x_quat (T, N, 4))``
    ``dt`` seconds apart; the mocap bodies at ``mocap = (mocap_pos, mocap_quat)``, :func:`mocap_track`) of
    ``scene`` to one HTML file that opens in a browser without torchsim (viser's client
    and the recording inlined; a local server for the duration of the call only, on ``127.0.0.1``).

    ``eye``/``target``/``fovy``: the initial camera (default: :meth:`Viewer.frame` on the first frame)."""
    viewer = Viewer(scene, host="127.0.0.1", port=8765, plane_extent=plane_extent, verbose=False)
    try:
        if eye is None:
            viewer.frame(None, fovy, body_poses(poses))
        else:
            viewer.set_camera(eye, body_poses(poses)[0][0].mean(0) if target is None else target, fovy)
        html = viewer.to_html(poses, dt, mocap)
    finally:
        viewer.close()
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(html)
    return path


def trajectory(system, qpos, batch: int = 256) -> tuple[torch.Tensor, torch.Tensor]:
    """Body poses ``(T, N, 3)``, ``(T, N, 4)`` of generalized coordinates ``qpos (T, nq)`` (``torchsim.init``,
    zero velocities), e.g. a recorded ``state.q`` trajectory."""
    import torchsim

    q = torch.as_tensor(np.asarray(qpos), dtype=system.q0.dtype, device=system.q0.device)
    pos, quat = [], []
    for start in range(0, len(q), batch):
        part = q[start:start + batch]
        state = torchsim.init(system, part, torch.zeros(len(part), system.nv, dtype=q.dtype, device=q.device))
        pos.append(state.x_pos)
        quat.append(state.x_quat)
    return torch.cat(pos), torch.cat(quat)


__all__ = ["PLANE_EXTENT", "Viewer", "body_poses", "geom_mesh", "is_loopback", "mocap_track", "save_html",
           "scene_geom_mesh", "trajectory"]
