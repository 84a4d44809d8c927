"""Closed-form ray hits of MuJoCo's primitive shapes, branch-free and batched.

Every function takes a ray expressed in the geom's own frame, ``origin + t direction``: ``o = (ox, oy, oz)``
tensors broadcastable to the result (one origin per camera and geom, e.g. ``(b, C, g, 1, 1)``) and
``d = (dx, dy, dz)`` (one direction per pixel, e.g. ``(b, C, g, H, W)``), the geom's MuJoCo ``size`` components
broadcastable likewise, and the clip range ``(znear, zfar)``. It returns the ray parameter ``t`` of the first
surface crossing with ``znear < t < zfar``, and ``inf`` where there is none. Directions need not be unit: the
renderer scales them so that ``t`` is the planar z-depth.

Shapes (MuJoCo's sizes): plane (half-sizes x, y; 0 means infinite; seen from both sides, as MuJoCo draws it),
sphere (radius), capsule (radius, half-length of the segment along z), ellipsoid (semi-axes), cylinder (radius,
half-height), box (half-sizes). The ray is assumed to start outside the solid shapes (a camera inside a geom sees
its far side only where the near crossing is clipped). Quadratics are solved through the point of closest approach
(``t_m = -o.d / d.d``), which keeps small, distant shapes accurate in float32.

:func:`normal` gives the outward surface normal at a hit point, for shading.
"""

import torch

INF = float("inf")


def _keep(t, ok, znear, zfar):
    return torch.where(ok & (t > znear) & (t < zfar), t, INF)


def _ball(o, d, r2):
    """Near crossing of the ray with the ball (circle in 2-D) ``|x|^2 = r2`` over the components given, and
    whether the ray meets it."""
    a = sum(di * di for di in d).clamp_min(1e-30)
    tm = -sum(oi * di for oi, di in zip(o, d)) / a
    q2 = sum((oi + tm * di) ** 2 for oi, di in zip(o, d))
    h2 = r2 - q2
    return tm - torch.sqrt(h2.clamp_min(0) / a), h2 >= 0


def _safe(x):
    """``x`` with exact zeros replaced by a tiny number of either sign (a ray parallel to a face)."""
    return torch.where(x == 0, 1e-30, x)


def plane(o, d, size, znear, zfar):
    t = -o[2] / d[2]  # a ray parallel to the plane: inf or nan, which _keep rejects
    x, y = o[0] + t * d[0], o[1] + t * d[1]
    ok = ((x.abs() <= size[0]) | (size[0] <= 0)) & ((y.abs() <= size[1]) | (size[1] <= 0))
    return _keep(t, ok, znear, zfar)


def sphere(o, d, size, znear, zfar):
    t, ok = _ball(o, d, size[0] * size[0])
    return _keep(t, ok, znear, zfar)


def ellipsoid(o, d, size, znear, zfar):
    t, ok = _ball([oi / s for oi, s in zip(o, size)], [di / s for di, s in zip(d, size)], 1.0)
    return _keep(t, ok, znear, zfar)


def _side(o, d, r, h):
    """Near crossing of the infinite cylinder of radius ``r`` about z, kept where it lies within ``|z| <= h``."""
    t, ok = _ball(o[:2], d[:2], r * r)
    ok = ok & ((d[0] * d[0] + d[1] * d[1]) > 1e-30) & ((o[2] + t * d[2]).abs() <= h)
    return t, ok


def capsule(o, d, size, znear, zfar):
    r, h = size[0], size[1]
    t, ok = _side(o, d, r, h)
    best = _keep(t, ok, znear, zfar)
    for s in (1.0, -1.0):  # the two end spheres: the first crossing of a union seen from outside is the least
        t, ok = _ball((o[0], o[1], o[2] - s * h), d, r * r)
        best = torch.minimum(best, _keep(t, ok, znear, zfar))
    return best


def cylinder(o, d, size, znear, zfar):
    r, h = size[0], size[1]
    t, ok = _side(o, d, r, h)
    best = _keep(t, ok, znear, zfar)
    dz = _safe(d[2])
    for s in (1.0, -1.0):  # the two flat caps
        t = (s * h - o[2]) / dz
        x, y = o[0] + t * d[0], o[1] + t * d[1]
        best = torch.minimum(best, _keep(t, x * x + y * y <= r * r, znear, zfar))
    return best


def box(o, d, size, znear, zfar):
    near = far = None
    for oi, di, si in zip(o, d, size):  # slabs
        inv = 1.0 / _safe(di)
        t1, t2 = (-si - oi) * inv, (si - oi) * inv
        lo, hi = torch.minimum(t1, t2), torch.maximum(t1, t2)
        near = lo if near is None else torch.maximum(near, lo)
        far = hi if far is None else torch.minimum(far, hi)
    return _keep(near, near <= far, znear, zfar)


HIT = {"plane": plane, "sphere": sphere, "capsule": capsule, "ellipsoid": ellipsoid, "cylinder": cylinder, "box": box}
#: Integer codes of the shapes (the order of ``HIT``), for per-pixel selection in :func:`normal`.
CODE = {k: i for i, k in enumerate(HIT)}


def normal(code, p, size, kinds=tuple(HIT)):
    """Outward normal (not normalised) ``(nx, ny, nz)`` at surface point ``p = (px, py, pz)`` (geom frame) of a
    geom of shape ``code`` (``CODE``) and ``size``; all tensors of one shape (per pixel). Only the shapes in
    ``kinds`` are considered (others get ``+z``)."""
    px, py, pz = p
    sx, sy, sz = size
    zero, one = torch.zeros_like(px), torch.ones_like(px)

    def candidate(kind):
        if kind == "plane":
            return zero, zero, one
        if kind == "sphere":
            return px, py, pz
        if kind == "capsule":  # from the nearest point of its segment
            return px, py, pz - pz.clamp(-sy, sy)
        if kind == "ellipsoid":
            return px / (sx * sx), py / (sy * sy), pz / (sz * sz)
        if kind == "cylinder":  # a cap where the point is nearer a cap's plane than the side
            cap = (sy - pz.abs()) < (sx - torch.sqrt(px * px + py * py))
            return torch.where(cap, zero, px), torch.where(cap, zero, py), torch.where(cap, torch.sign(pz), zero)
        ax, ay, az = px.abs() / sx, py.abs() / sy, pz.abs() / sz  # box: the face of the largest scaled coordinate
        fx = (ax >= ay) & (ax >= az)
        fy = ~fx & (ay >= az)
        return (torch.where(fx, torch.sign(px), zero), torch.where(fy, torch.sign(py), zero),
                torch.where(fx | fy, zero, torch.sign(pz)))

    n = (zero, zero, one)
    for kind in kinds:
        n = tuple(torch.where(code == CODE[kind], v, ni) for v, ni in zip(candidate(kind), n))
    return n
