"""The nearest hit of every pixel's ray over all geoms, for one chunk of envs: dense, or culled by screen tiles.

Both paths first express each geom's centre and axes in each camera's frame (per env, camera and geom), which
gives the ray in the geom's frame: origin ``o_l = -E^T c`` (one per camera and geom) and direction components
``d_l[k] = E[0, k] X + E[1, k] Y - E[2, k]`` (a per-column plus a per-row term: no matrix product per pixel).

``dense`` tests every pixel against every geom, one batched call per shape type; it has no data-dependent shapes.
``tiled`` splits the image into ``T x T`` tiles and first tests each geom's bounding sphere against each tile's
frustum (the four planes through the camera and the tile's outermost pixel-centre rays, and the clip range); only
the surviving (env, camera, geom, tile) rows are ray cast, and their hits are reduced into the image with a
scatter-min. Most geoms of a robot cover a few tiles of a 64x64 image, so this does a fraction of the dense work,
and gives the same images (the culling is conservative). The geom seen by a pixel is found with the same
scatter-min on a key packing the hit's float32 depth bits above the geom's index.

Mesh geoms take the same paths: their rays (the same origin and per-pixel directions in the geom's frame) go
through the mesh's BVH (:func:`torchsim.render.mesh.cast`) instead of a closed form, always eagerly, after the
closed-form shapes: each ray skips the boxes behind the depth its pixel already has. (Casting a robot's mesh
rows in batches, nearest geoms first, to skip parts hidden behind nearer meshes, measured no faster on robosuite's
Panda: 20% fewer leaf tests, the same time.)
"""

import torch

from torchsim.render import mesh, raycast

NONE = 0xFFFF  # the "no geom" index in packed keys (scenes have fewer geoms)
EMPTY = (0x7F800000 << 16) | NONE  # the key of no hit: float32 +inf's bits, no geom


def in_camera(cam_pos, cam_rot, geom_pos, geom_rot):
    """Geom centres ``c (b, C, G, 3)`` and axes ``E (b, C, G, 3, 3)`` in each camera's frame, and the cameras'
    ray origin in each geom's frame ``o_l (b, C, G, 3)``."""
    centre = torch.einsum("bcji,bcgj->bcgi", cam_rot, geom_pos[:, None] - cam_pos[:, :, None])
    axes = torch.einsum("bcji,bgjk->bcgik", cam_rot, geom_rot)
    return centre, axes, -torch.einsum("bcgik,bcgi->bcgk", axes, centre)


def _directions(e, x, y):
    """Ray directions in geom frames from axes ``e (..., 3, 3)`` (broadcast against the slopes ``x``, ``y``)."""
    return tuple(e[..., 0, k] * x + e[..., 1, k] * y - e[..., 2, k] for k in range(3))


def _rows(kind, o, e, x, y, size, znear, zfar):
    """Hits ``t (K, T, T)`` of ``K`` (camera, geom, tile) rows: ray origins ``o (K, 3)``, geom axes
    ``e (K, 3, 3)``, the tile's slopes ``x (K, T)``, ``y (K, T)``, sizes ``size (K, 3)``."""
    o = tuple(o[:, k, None, None] for k in range(3))
    d = _directions(e[:, None, None], x[:, None, :], y[:, :, None])
    size = tuple(size[:, k, None, None] for k in range(3))
    return raycast.HIT[kind](o, d, size, znear, zfar)


# One function (code object) per shape, so that torch.compile keeps a separate cache for each.
def _plane_rows(*args): return _rows("plane", *args)  # noqa: E704
def _sphere_rows(*args): return _rows("sphere", *args)  # noqa: E704
def _capsule_rows(*args): return _rows("capsule", *args)  # noqa: E704
def _ellipsoid_rows(*args): return _rows("ellipsoid", *args)  # noqa: E704
def _cylinder_rows(*args): return _rows("cylinder", *args)  # noqa: E704
def _box_rows(*args): return _rows("box", *args)  # noqa: E704


ROWS = {"plane": _plane_rows, "sphere": _sphere_rows, "capsule": _capsule_rows, "ellipsoid": _ellipsoid_rows,
        "cylinder": _cylinder_rows, "box": _box_rows}
_COMPILED = {}


def rows_function(kind: str, compiled: bool):
    """:func:`_rows` for shape ``kind``, eager or through ``torch.compile`` (fused loops: the hit test's few
    dozen elementwise operations become one pass over memory; compiled once per shape type and process, with
    dynamic shapes; pass the clip distances as tensors so that scenes share the compiled code)."""
    if not compiled:
        return ROWS[kind]
    if kind not in _COMPILED:
        _COMPILED[kind] = torch.compile(ROWS[kind], dynamic=True)
    return _COMPILED[kind]


def dense(scene, origin, axes, xs, ys, want_which: bool):
    """Depth ``(b, C, H, W)`` (inf: no hit) and, if asked, the scene geom index hit (-1: none)."""
    b, c = origin.shape[:2]
    h, w = ys.shape[1], xs.shape[1]
    x, y = xs[None, :, None, None, :], ys[None, :, None, :, None]
    depth = origin.new_full((b, c, h, w), float("inf"))
    which = torch.full((b, c, h, w), -1, dtype=torch.long, device=origin.device) if want_which else None
    for kind, index in scene.groups:
        o = tuple(origin[:, :, index, k, None, None] for k in range(3))
        d = _directions(axes[:, :, index, None, None], x, y)
        if kind == "mesh":
            t = _mesh_dense(scene, index, o, d, depth)
        else:
            size = tuple(scene.geom_size[index, k][:, None, None] for k in range(3))
            t = raycast.HIT[kind](o, d, size, scene.znear, scene.zfar)
        t, arg = t.min(2)
        if want_which:
            which = torch.where(t < depth, index[arg], which)
        depth = torch.minimum(depth, t)
    return depth, which


def _mesh_dense(scene, index, o, d, depth):
    """Hits ``(b, C, g, H, W)`` of every pixel's ray with the mesh geoms ``index`` (ray components as in
    :func:`dense`; hits behind ``depth (b, C, H, W)`` are not needed)."""
    d = torch.stack(torch.broadcast_tensors(*d), -1)
    o = torch.stack(o, -1).expand_as(d)
    which = scene.geom_mesh[index][None, None, :, None, None].expand(d.shape[:-1])
    limit = depth[:, :, None].expand(d.shape[:-1])
    t, _ = mesh.cast(scene.meshes, which.reshape(-1), o.reshape(-1, 3), d.reshape(-1, 3), scene.znear, scene.zfar,
                     limit=limit.reshape(-1))
    return t.view(d.shape[:-1])  # hits behind ``depth`` may be any value above it: they change nothing


def tiled(scene, centre, origin, axes, xs, ys, tile: int, want_which: bool, compiled: bool = False):
    """:func:`dense`'s result, computed only where a geom's bounding sphere may reach a ``tile x tile`` tile."""
    b, c = origin.shape[:2]
    h, w = ys.shape[1], xs.shape[1]
    if want_which and scene.num_geoms >= NONE:
        raise ValueError(f"segmentation with tiles packs geom indices in 16 bits: {scene.num_geoms} geoms is too many "
                         "(render with tile=0)")
    ty, tx = -(-h // tile), -(-w // tile)
    xt, yt = _pad(xs, tx * tile).view(c, tx, tile), _pad(ys, ty * tile).view(c, ty, tile)
    planes = [(xt.amin(-1), 1.0), (xt.amax(-1), -1.0)], [(yt.amin(-1), 1.0), (yt.amax(-1), -1.0)]
    tiles = b * c * ty * tx
    depth = origin.new_full((tiles * tile * tile,), float("inf"))
    key = torch.full_like(depth, EMPTY, dtype=torch.long) if want_which else None
    lane = torch.arange(tile * tile, device=origin.device)
    clip = origin.new_tensor([scene.znear, scene.zfar]).unbind()
    for kind, index in scene.groups:
        cen, radius = centre[:, :, index], scene.geom_radius[index] * 1.0001 + 1e-9
        z = -cen[..., 2]  # distance ahead of the camera
        keep = (z + radius > scene.znear) & (z - radius < scene.zfar)
        # the geom's bounding sphere against the tile's side planes: X >= lo is x + lo z' >= 0 with z' = cz
        sides = []
        for axis, bounds in enumerate(planes):
            ok = None
            for bound, sign in bounds:
                bound = bound[None, :, None, :]  # (1, C, 1, tiles)
                dist = sign * (cen[..., axis, None] + bound * cen[..., 2, None]) / torch.sqrt(1 + bound * bound)
                ok = dist >= -radius[:, None] if ok is None else ok & (dist >= -radius[:, None])
            sides.append(ok)
        mask = keep[..., None, None] & sides[1][..., :, None] & sides[0][..., None, :]  # (b, C, g, TY, TX)
        bi, ci, gi, yi, xi = mask.nonzero(as_tuple=True)
        if bi.numel() == 0:
            continue
        geom = index[gi]
        pixel = ((((bi * c + ci) * ty + yi) * tx + xi) * (tile * tile))[:, None] + lane
        if kind == "mesh":  # each ray skips what lies behind its pixel's depth so far (the closed-form shapes')
            t = mesh.rows(scene.meshes, scene.geom_mesh[geom], origin[bi, ci, geom], axes[bi, ci, geom], xt[ci, xi],
                          yt[ci, yi], scene.znear, scene.zfar, limit=depth[pixel].view(-1, tile, tile))
            t = t.reshape(-1, tile * tile)
        else:
            t = rows_function(kind, compiled)(origin[bi, ci, geom], axes[bi, ci, geom], xt[ci, xi], yt[ci, yi],
                                              scene.geom_size[geom], clip[0], clip[1]).reshape(-1, tile * tile)
        depth.scatter_reduce_(0, pixel.reshape(-1), t.reshape(-1), "amin")
        if want_which:
            key.scatter_reduce_(0, pixel.reshape(-1), _pack(t, geom[:, None]).reshape(-1), "amin")
    depth = _untile(depth, b, c, ty, tx, tile)[:, :, :h, :w]
    if not want_which:
        return depth, None
    which = _untile(key & NONE, b, c, ty, tx, tile)[:, :, :h, :w]
    return depth, torch.where(torch.isfinite(depth), which, -1)  # a miss packs inf above its geom's index


def _pack(t, geom):
    """Keys ordered by depth, then geom: float32 bits of ``t >= 0`` (ordered as integers) above the geom index."""
    bits = t.float().view(torch.int32).to(torch.long)
    return (bits << 16) | geom


def _pad(slopes, n):
    """Slopes ``(C, k)`` extended to ``n`` columns by continuing their even spacing (pixels past the image edge,
    cropped afterwards)."""
    k = slopes.shape[1]
    if n == k:
        return slopes
    step = slopes[:, 1:2] - slopes[:, :1] if k > 1 else torch.ones_like(slopes[:, :1])
    extra = slopes[:, -1:] + step * torch.arange(1, n - k + 1, dtype=slopes.dtype, device=slopes.device)
    return torch.cat((slopes, extra), 1)


def _untile(flat, b, c, ty, tx, tile):
    return flat.view(b, c, ty, tx, tile, tile).permute(0, 1, 2, 4, 3, 5).reshape(b, c, ty * tile, tx * tile)
