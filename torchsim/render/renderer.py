"""``render``: depth, segmentation and RGB images of every env's cameras in one call, by ray casting.

Per env only body poses change: the body frames are read from the state (and the mocap bodies' from the given
mocap poses), the cameras and geoms placed on them,
and every pixel's ray (through the pixel centre, MuJoCo's pinhole convention: :mod:`torchsim.render.camera`) is
intersected with the geoms in closed form (:mod:`torchsim.render.raycast`), keeping the nearest hit
(:mod:`torchsim.render.nearest`: culled by screen tiles by default). Colour, where asked, is the hit geom's colour
under a headlight. Envs are processed in chunks (``max_tests``) so memory stays bounded at any batch size.
"""

from typing import NamedTuple

import torch

from torchsim.render import mesh, nearest, raycast
from torchsim.render.camera import Camera, pixel_rays
from torchsim.render.frames import body_frames, place
from torchsim.render.scene import Scene


class Images(NamedTuple):
    """Rendered images; ``C`` is dropped where a single camera was asked for (see :func:`render`).

    Attributes:
        depth: (B, C, H, W) planar z-depth [m] (distance along the camera's viewing axis, not along the ray);
            pixels that see nothing hold ``background_depth`` (default ``scene.zfar``, as MuJoCo's depth buffer).
        segmentation: (B, C, H, W) int64 MuJoCo geom id seen by each pixel, -1 for none (None unless asked).
        rgb: (B, C, H, W, 3) colour in [0, 1] (None unless asked).
    """

    depth: torch.Tensor
    segmentation: torch.Tensor | None
    rgb: torch.Tensor | None


def render(scene: Scene, state, camera=0, height: int = 64, width: int = 64, *, segmentation: bool = True,
           rgb: bool = False, shading: str = "lambert", ambient: float = 0.3, diffuse: float = 0.7,
           background_depth: float | None = None, background_rgb=(0.0, 0.0, 0.0), tile: int = 8,
           compile: bool = False, max_tests: int | None = None, mocap_pos: torch.Tensor | None = None,
           mocap_quat: torch.Tensor | None = None) -> Images:
    """Images of ``camera`` in every env of ``state``.

    Args:
        scene: the model's :class:`Scene` (``Scene.build(model, system)``).
        state: a ``torchsim.State`` (only ``x_pos (B, N, 3)`` and ``x_quat (B, N, 4)`` are read) or a pair
            ``(x_pos, x_quat)``.
        camera: a model camera's index or name, a :class:`Camera` (e.g. ``Camera.look_at``), or a list of these.
            A single index, name or one-camera :class:`Camera` gives images without the ``C`` dimension
            (``(B, H, W)``); a list always keeps it (``(B, C, H, W)``).
        height, width: image size in pixels.
        segmentation: also return the geom-id image.  rgb: also return colour images: the geom's colour (its
            ``rgba``, or its material's; textures are ignored), ``flat`` or ``lambert`` shaded (``ambient +
            diffuse |cos|`` of the angle between the surface normal and the ray: a headlight at the camera).
        background_depth: depth of empty pixels (default ``scene.zfar``).  background_rgb: their colour.
        tile: side of the screen tiles against which geoms' bounding spheres are culled before ray casting
            (:func:`torchsim.render.nearest.tiled`); 0 tests every pixel against every geom (no data-dependent
            shapes, e.g. for ``torch.compile``). Both give the same images.
        compile: run the tiled path's hit tests through ``torch.compile`` (one fused loop per shape type instead
            of dozens of passes over memory: several times faster at large batches; the first call per shape type
            and process compiles, a few seconds each, then cached on disk by inductor). Depths may differ from the
            eager ones by float rounding (~1e-6 relative).
        max_tests: bound on the ray-geom tests of one chunk of envs, counted as if nothing were culled (memory:
            roughly 80-100 bytes each in float32 without culling, ~2-3 with it). Default on a CPU: 2^23 with
            tiles (the ant at 64x64: 146 envs per chunk, ~0.1 GiB), 2^22 without; on a GPU 2^27 and 2^24 (fewer,
            larger chunks: a GPU's call is launch-bound below a few thousand envs).
        mocap_pos, mocap_quat: the mocap bodies' poses, ``(B, K, 3)``, ``(B, K, 4)`` per env or ``(K, 3)``,
            ``(K, 4)`` for all (the System's ``mocap_pos``/``mocap_quat``, which the step reads: pass them where
            they were set); default, either: the model's (``scene.mocap_pos``/``mocap_quat``). The geoms and
            cameras of mocap bodies, and of the jointless bodies fused into them, are drawn at these poses.

    Geoms nearer than ``scene.znear`` or farther than ``scene.zfar`` are clipped, as in MuJoCo's renderer.
    Computation is in the state's dtype and on its device.
    """
    if shading not in ("flat", "lambert"):
        raise ValueError(f"shading must be 'flat' or 'lambert', got {shading!r}")
    x_pos, x_quat = (state.x_pos, state.x_quat) if hasattr(state, "x_pos") else state
    if x_pos.ndim != 3 or x_pos.shape[1] != scene.num_bodies:
        raise ValueError(f"expected body positions (B, {scene.num_bodies}, 3), got {tuple(x_pos.shape)}")
    cams = scene.camera(camera)
    squeeze = (isinstance(camera, Camera) or not isinstance(camera, (list, tuple))) and cams.num == 1
    if scene.geom_pos.dtype != x_pos.dtype or scene.geom_pos.device != x_pos.device:
        scene = scene.to(x_pos.device, x_pos.dtype)
    # a camera's -1 stands for the world (Camera.look_at): frame N, the mocap frames following it
    cams = cams._replace(body=torch.where(cams.body < 0, scene.num_bodies, cams.body)).to(x_pos.device, x_pos.dtype)
    mocap_pos = _mocap(mocap_pos, scene.mocap_pos, x_pos, 3, "mocap_pos")
    mocap_quat = _mocap(mocap_quat, scene.mocap_quat, x_pos, 4, "mocap_quat")
    xs, ys = pixel_rays(cams.fovy, height, width)
    background = scene.zfar if background_depth is None else float(background_depth)
    batch, per_env = x_pos.shape[0], max(1, cams.num * scene.num_geoms * height * width)
    if max_tests is None:
        gpu = x_pos.device.type != "cpu"
        max_tests = 1 << ((27 if gpu else 23) if tile else (24 if gpu else 22))
    chunk = max(1, int(max_tests) // per_env)
    outs = []
    for start in range(0, batch, chunk):
        pos, rot = body_frames(x_pos[start:start + chunk], x_quat[start:start + chunk],
                               mocap_pos[start:start + chunk], mocap_quat[start:start + chunk])
        cam_pos, cam_rot = cams.poses(pos, rot)
        geom_pos, geom_rot = place(pos, rot, scene.geom_body, scene.geom_pos, scene.geom_rot)
        outs.append(_images(scene, cam_pos, cam_rot, geom_pos, geom_rot, xs, ys, background, segmentation, rgb,
                            int(tile), bool(compile), shading, ambient, diffuse, background_rgb))
    depth, seg, colour = (torch.cat(parts) if parts[0] is not None else None for parts in zip(*outs))
    if squeeze:
        depth, seg, colour = (x[:, 0] if x is not None else None for x in (depth, seg, colour))
    return Images(depth, seg, colour)


def _mocap(given, model, x_pos, width, label):
    """Mocap poses ``(B, K, width)`` in ``x_pos``'s dtype and device: ``given`` per env or shared, or ``model``'s."""
    batch, count = x_pos.shape[0], model.shape[0]
    value = model if given is None else torch.as_tensor(given)
    if value.shape[-2:] != (count, width) or value.ndim not in (2, 3) or (value.ndim == 3 and value.shape[0] != batch):
        raise ValueError(f"{label} must be ({count}, {width}) or ({batch}, {count}, {width}) for this scene's {count} "
                         f"mocap bodies and {batch} envs, got {tuple(value.shape)}")
    return value.to(x_pos.device, x_pos.dtype).expand(batch, count, width)


def _images(scene, cam_pos, cam_rot, geom_pos, geom_rot, xs, ys, background, want_seg, want_rgb, tile, compiled,
            shading, ambient, diffuse, background_rgb):
    """Images of one chunk of envs: cameras at ``cam_pos (b, C, 3)``, ``cam_rot (b, C, 3, 3)``, geoms at
    ``geom_pos (b, G, 3)``, ``geom_rot (b, G, 3, 3)``."""
    centre, axes, origin = nearest.in_camera(cam_pos, cam_rot, geom_pos, geom_rot)
    want_which = want_seg or want_rgb
    if tile:
        depth, which = nearest.tiled(scene, centre, origin, axes, xs, ys, tile, want_which, compiled)
    else:
        depth, which = nearest.dense(scene, origin, axes, xs, ys, want_which)
    hit = torch.isfinite(depth)
    seg = torch.where(hit, scene.geom_id[which.clamp_min(0)], -1) if want_seg else None
    rgb = _shade(scene, axes, origin, depth, which, xs, ys, shading, ambient, diffuse, background_rgb) \
        if want_rgb else None
    return torch.where(hit, depth, background), seg, rgb


def _shade(scene, axes, origin, depth, which, xs, ys, shading, ambient, diffuse, background_rgb):
    """Colour ``(b, C, H, W, 3)`` of the nearest hits ``depth``, ``which`` (scene geom positions, -1 none)."""
    hit = which >= 0
    k = which.clamp_min(0)
    colour = scene.geom_rgba[:, :3][k]
    if shading == "lambert":
        b, c, h, w = k.shape
        g = axes.shape[2]
        rows = (torch.arange(b * c, device=k.device).view(b, c, 1, 1) * g + k).reshape(-1)
        e = axes.reshape(-1, 3, 3).index_select(0, rows).view(b, c, h, w, 3, 3).unbind(-2)  # rows of E
        o = origin.reshape(-1, 3).index_select(0, rows).view(b, c, h, w, 3).unbind(-1)
        x, y = xs[None, :, None, :], ys[None, :, :, None]
        d = tuple(e[0][..., j] * x + e[1][..., j] * y - e[2][..., j] for j in range(3))  # ray, geom frame
        t = torch.where(hit, depth, 0.0)
        p = tuple(oj + t * dj for oj, dj in zip(o, d))
        codes = torch.as_tensor([raycast.CODE.get(kind, -1) for kind in scene.geom_type], device=k.device)[k]
        size = scene.geom_size[k].unbind(-1)
        n = raycast.normal(codes, p, size, kinds=[kind for kind, _ in scene.groups if kind in raycast.CODE])
        if scene.meshes is not None:
            n = _mesh_normals(scene, k, hit, o, d, t, n)
        n_cam = tuple(e[i][..., 0] * n[0] + e[i][..., 1] * n[1] + e[i][..., 2] * n[2] for i in range(3))
        dot = n_cam[0] * x + n_cam[1] * y - n_cam[2]
        norms = (n_cam[0] ** 2 + n_cam[1] ** 2 + n_cam[2] ** 2) * (x * x + y * y + 1)
        cos = dot.abs() / torch.sqrt(norms).clamp_min(1e-12)
        colour = colour * (ambient + diffuse * cos)[..., None]
    back = torch.as_tensor(background_rgb, dtype=colour.dtype, device=colour.device)
    return torch.where(hit[..., None], colour.clamp(0, 1), back)


def _mesh_normals(scene, k, hit, o, d, t, n):
    """``n`` with the face normals of the mesh triangles seen by the pixels that see a mesh geom: their rays
    (``o``, ``d``: geom frame) are cast again through their geom's BVH, visiting only the boxes around the hit at
    depth ``t``, this time asking for the triangle."""
    which = scene.geom_mesh[k]
    index = (hit & (which >= 0)).reshape(-1).nonzero().squeeze(1)
    if index.numel() == 0:
        return n
    o, d = (torch.stack(torch.broadcast_tensors(*v), -1).reshape(-1, 3)[index] for v in (o, d))
    _, tri = mesh.cast(scene.meshes, which.reshape(-1)[index], o, d, scene.znear, scene.zfar, want_tri=True,
                       at=t.reshape(-1)[index])
    face = scene.meshes.normal[tri.clamp_min(0)]
    return tuple(ni.reshape(-1).index_put((index,), face[:, j]).view(ni.shape)
                 for j, ni in enumerate(torch.broadcast_tensors(*n)))


__all__ = ["Images", "render", "Camera"]
