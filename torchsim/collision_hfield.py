"""Contact geometry of height fields (MuJoCo ``<hfield>`` geoms, static on the world; ``torchsim.collision``
dispatches here).

The surface is MuJoCo's: grid vertex ``(row, col)`` of an ``nrow x ncol`` field with ``size = (sx, sy, sz, base)``
lies at ``x = col dx - sx``, ``y = row dy - sy`` (``dx = 2 sx / (ncol - 1)``, ``dy = 2 sy / (nrow - 1)``) and
``z = data[row ncol + col] sz`` in the geom frame (``System.hfield_height`` holds ``data sz``), and each cell is
split along the diagonal from ``(row, col)`` to ``(row + 1, col + 1)`` into two triangles (MuJoCo's
``mjc_ConvexHField``, which collides the geom with each triangle's prism down to ``-base``).

Only a fixed window of cells around each geom is tested: ``Wy x Wx`` cells (``System.hfield_windows``, per pair
kind, from the load: ``floor(2 (rbound + margin) / d) + 2`` cells along each axis, the most cells the geom's
bounding sphere can overlap, capped at the grid), starting at the cell under the low corner of the geom's bounding
square (in the field's frame), clamped into the grid. Cells of the window past a smaller grid's end are masked.

A point ``x`` with radius ``r`` is tested against every triangle of its window (:func:`_point_triangles`):
above the triangle's plane, the distance to the triangle's nearest point (exact, normal along it); below it,
where ``x`` lies in the triangle's vertical prism, the depth below its plane (MuJoCo's prism top face; the prism's
side walls and base are not modelled), with the triangle's normal; else no contact. Per pair, the
deepest contacts are kept in a fixed number of slots (``POINTS_PER_PAIR``, ``torchsim.system``):
- sphere: its centre; the 4 deepest triangles (a sphere in a valley touches both sides) (4 slots);
- capsule: 5 spheres along its segment (ends, quarters, middle); the 2 deepest triangles of each (10);
- box: its 8 corners, the deepest triangle of each, and the 4 deepest grid vertices inside the box (exact
  point-box distance, the terrain's peaks into a face) (12);
- ellipsoid: its support point along each triangle's inward normal against that triangle, the 4 deepest, and the
  2 deepest grid vertices inside it (6);
- cylinder: its 8 cap rim points at quarter turns from the lowest in the field's frame (as on a plane), the
  deepest triangle of each, its support point along each triangle's inward normal (the 2 deepest) and the 2
  deepest grid vertices inside it (12).
A sphere across a cell edge or vertex gets one contact per triangle it overlaps, as MuJoCo's prisms do (their
normals tilt towards the shared edge; the 4 deepest are kept). Meshes against height fields are refused by the
loader. Edges of the terrain crossing a box, ellipsoid or cylinder between grid vertices (a sharp ridge under a
flat face) are missed; ``tests/test_hfield.py`` measures the contacts against MuJoCo's.

Cost: every candidate point meets every triangle of its window (``P x points x 2 Wy Wx x B``), ranked by scalar
distances alone (:func:`_distances`); only the kept ones get a point and normal. Eager, dm_control's quadruped at
256 envs spends about 28 ms of its 42 ms of contacts on its 20 height-field pairs, 18 ms on the 12 capsules' (5
points x 18 triangles each; 2-core shared CPU, float32, noisy; 50 of 67 ms before the ranking pass). Work is static
and branch-free (``torch.where``); the window's elevations are gathered from the field by index, which the step
kernel's row graphs cannot express: the kernel refuses models with height fields (they run on ``loop``: a sphere on
a field compiled in 72-82 s and stepped as the eager step to 5e-11 m).
"""

import torch

from torchsim import collision_round, lanes, spatial

#: The distance [m] given to candidates that are not contacts (masked cells, points beside a triangle below it).
PADDING_DISTANCE = 1.0
_CAPSULE_POINTS = (0.0, 0.25, 0.5, 0.75, 1.0)


def window(rbound: float, cell: float, cells: int) -> int:
    """Cells along one axis of the window for a geom of bounding radius ``rbound`` (plus margin) [m] over a grid
    of ``cells`` cells of width ``cell`` [m]: the most its bounding interval can overlap, capped at the grid."""
    return int(min(int(2.0 * rbound // cell) + 2, cells))


def rbound(shape: str, size: torch.Tensor) -> torch.Tensor:
    """MuJoCo's ``geom_rbound`` of primitives of ``shape`` from their sizes ``(3, ...)``."""
    if shape == "sphere":
        return size[0]
    if shape == "capsule":
        return size[0] + size[1]
    if shape == "ellipsoid":
        return size.amax(0)
    if shape == "cylinder":
        return (size[0] * size[0] + size[1] * size[1]).sqrt()
    return spatial.safe_norm(size, 0.0)


def _closest_on_segment(p0, p1, x):
    d = p1 - p0
    t = torch.clamp(spatial.dot(x - p0, d) / spatial.dot(d, d).clamp_min(1e-12), 0.0, 1.0)
    return p0 + t * d


def _point_triangles(x, r, tri, normal, valid):
    """Spheres of radius ``r`` at ``x (3, P, M, T|1, B)`` against triangles ``tri`` (3 vertices ``(3, P, 1, T, B)``,
    counter-clockwise seen from above) with upward unit normals ``normal``, ``valid (P, 1, T, B)``: (point, normal
    triangle->sphere, distance ``(P, M, T, B)``), as the module docstring."""
    a, b, c = tri
    s = spatial.dot(x - a, normal)
    proj = x - s * normal
    inside_proj, inside_xy = True, True  # x projected along the normal, or vertically, lies in the triangle
    edges = ((a, b), (b, c), (c, a))
    for p, q in edges:
        e = q - p
        inside_proj = inside_proj & (spatial.dot(spatial.cross(e, proj - p), normal) >= 0)
        inside_xy = inside_xy & (e[0] * (x[1] - p[1]) - e[1] * (x[0] - p[0]) >= 0)
    near = [_closest_on_segment(p, q, x) for p, q in edges]
    gaps = [spatial.safe_norm(x - q) for q in near]
    first = (gaps[0] <= gaps[1]) & (gaps[0] <= gaps[2])
    second = ~first & (gaps[1] <= gaps[2])
    on_edge = torch.where(first, near[0], torch.where(second, near[1], near[2]))
    nearest = torch.where(inside_proj, proj, on_edge)
    gap = spatial.safe_norm(x - nearest)
    above = s >= 0
    n_above = torch.where(gap > 1e-9, (x - nearest) / gap, normal)
    dist = torch.where(above, gap - r, torch.where(inside_xy, s - r, PADDING_DISTANCE))
    dist = torch.where(valid, dist, PADDING_DISTANCE)
    n = torch.where(above, n_above, normal).expand(x.shape[:1] + dist.shape)
    return x - n * (r + 0.5 * dist), n, dist


def _distances(x, r, tri, normal, valid):
    """:func:`_point_triangles`' distances alone ``(P, M, T, B)``, from scalar fields (edge distances squared from
    dot products, the inside tests as triple products with per-triangle vectors): the ranking pass, which never
    builds a contact point or normal per candidate."""
    s = spatial.dot(x - tri[0], normal)
    inside_proj, inside_xy, gap2 = True, True, None
    for p, q in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
        e, xp = q - p, x - p
        inside_proj = inside_proj & (spatial.dot(xp, spatial.cross(normal, e)) >= 0)
        inside_xy = inside_xy & (e[0] * xp[1] - e[1] * xp[0] >= 0)
        along, length2 = spatial.dot(xp, e), spatial.dot(e, e).clamp_min(1e-12)
        t = torch.clamp(along / length2, 0.0, 1.0)
        g2 = spatial.dot(xp, xp) - 2 * t * along + t * t * length2
        gap2 = g2 if gap2 is None else torch.minimum(gap2, g2)
    gap = (torch.where(inside_proj, s * s, gap2).clamp_min(0.0) + 1e-12).sqrt()
    dist = torch.where(s >= 0, gap - r, torch.where(inside_xy, s - r, PADDING_DISTANCE))
    return torch.where(valid, dist, PADDING_DISTANCE)


def _deepest_triangles(x, r, tri, normal, valid, k):
    """The ``k`` deepest triangles for each point ``x (3, P, M, 1, B)`` (or each triangle's own point,
    ``(3, P, 1, T, B)``) as contacts ``(3, P, M k, B)`` (:func:`_deepest`'s layout): ranked by :func:`_distances`,
    then only the chosen ones evaluated by :func:`_point_triangles` (which the gradient flows through)."""
    dist = _distances(x, r, tri, normal, valid)
    k = min(k, dist.shape[-2])
    idx = torch.topk(dist, k, dim=-2, largest=False).indices  # (P, M, k, B)

    def pick(t):  # t: (3|, P, 1|M, T, B) -> (3|, P, M, k, B)
        lead = t.shape[:1] if t.ndim == idx.ndim + 1 else ()
        t = t.expand(*lead, *dist.shape[:-2], t.shape[-2], dist.shape[-1])
        return t.gather(-2, idx.expand(*lead, *idx.shape))

    x = pick(x) if x.shape[-2] > 1 else x
    pt, n, d = _point_triangles(x, r, [pick(v) for v in tri], pick(normal), pick(valid))
    return pt.flatten(-3, -2), n.flatten(-3, -2), d.flatten(-3, -2)


def _deepest(pt, n, dist, k, dim):
    """The ``k`` deepest (least distance) contacts along axis ``dim`` (negative) of ``dist (P, M, T, B)`` and of
    ``pt, n (3, P, M, T, B)``, flattened with the axis before it into one point axis ``(3, P, M k, B)``."""
    k = min(k, dist.shape[dim])
    dist, idx = torch.topk(dist, k, dim=dim, largest=False)
    pick = idx.unsqueeze(0).expand(3, *idx.shape)
    pt, n = pt.gather(dim, pick), n.gather(dim, pick)
    return pt.flatten(-3, -2), n.flatten(-3, -2), dist.flatten(-3, -2)


def _grid(sys, geom, local, rb, wy, wx):
    """The window's grid vertices ``(3, P, V, B)`` in the field's frame, their validity ``(P, V, B)``, its triangles
    (3 vertices ``(3, P, 1, T, B)``), their upward normals and validity ``(P, 1, T, B)``, for geoms at ``local
    (3, P, B)`` (field frame) with bounding radii ``rb (P, 1|B)``."""
    adr = sys.geom_hfield_adr[geom].unsqueeze(-1)  # (P, 1)
    nrow, ncol = (x.unsqueeze(-1) for x in sys.geom_hfield_grid[geom].unbind(-1))
    size = lanes.param(sys.geom_hfield_size, 1, 1).index_select(-2, geom)  # (4, P, 1)
    dx, dy = 2 * size[0] / (ncol - 1), 2 * size[1] / (nrow - 1)
    c0 = torch.floor((local[0] - rb + size[0]) / dx).long()
    r0 = torch.floor((local[1] - rb + size[1]) / dy).long()
    c0 = torch.minimum(c0.clamp_min(0), (ncol - 1 - wx).clamp_min(0))
    r0 = torch.minimum(r0.clamp_min(0), (nrow - 1 - wy).clamp_min(0))
    i = torch.arange(wy + 1, device=local.device).view(1, -1, 1, 1)
    j = torch.arange(wx + 1, device=local.device).view(1, 1, -1, 1)
    row, col = r0.unsqueeze(1).unsqueeze(1) + i, c0.unsqueeze(1).unsqueeze(1) + j  # (P, wy+1, wx+1, B)
    nrow4, ncol4 = nrow.view(-1, 1, 1, 1), ncol.view(-1, 1, 1, 1)
    row_in, col_in = row.clamp_max(nrow4 - 1), col.clamp_max(ncol4 - 1)
    z = sys.hfield_height[adr.view(-1, 1, 1, 1) + row_in * ncol4 + col_in]
    size4 = size.view(4, -1, 1, 1, 1)
    dx4, dy4 = dx.view(-1, 1, 1, 1), dy.view(-1, 1, 1, 1)
    vert = torch.stack(torch.broadcast_tensors(col_in.to(z) * dx4 - size4[0], row_in.to(z) * dy4 - size4[1], z))
    vert_valid = (row < nrow4) & (col < ncol4)
    cell_valid = ((row < nrow4 - 1) & (col < ncol4 - 1))[:, :-1, :-1]
    p00, p10 = vert[:, :, :-1, :-1], vert[:, :, :-1, 1:]
    p01, p11 = vert[:, :, 1:, :-1], vert[:, :, 1:, 1:]
    # MuJoCo's two triangles of a cell, counter-clockwise from above: (p00, p11, p01) and (p00, p10, p11)
    tri = [torch.stack(pair, -2).flatten(2, 4).unsqueeze(2) for pair in ((p00, p00), (p11, p10), (p01, p11))]
    normal = spatial.normalize(spatial.cross(tri[1] - tri[0], tri[2] - tri[0]))
    valid = torch.stack((cell_valid, cell_valid), -2).flatten(1, 3).unsqueeze(1)
    return vert.flatten(2, 3), vert_valid.flatten(1, 2), tri, normal, valid


def pair_contacts(sys, kind, geom_b, margin, pa, rot_a, sa, pb, rot_b, box_corners, point_box):
    """Contacts of primitives ``a`` at ``pa (3, P, B)``, ``rot_a (3, 3, P, B)``, sizes ``sa (3, P, 1)`` with the
    height fields ``geom_b (P,)`` posed at ``pb (3, P, 1)``, ``rot_b (3, 3, P, 1)``; ``margin (P, 1|B)``. Returns
    point, normal (field towards ``a``) ``(3, P, K, B)`` and distance ``(P, K, B)``, ``K`` the kind's
    ``torchsim.system.POINTS_PER_PAIR``.
    ``box_corners``, ``point_box``: ``torchsim.collision``'s (which imports this module)."""
    shape = kind[:-len("_hfield")]
    wy, wx = dict((k, (y, x)) for k, y, x in sys.hfield_windows)[kind]
    to_local = spatial.transpose(rot_b)
    local = spatial.matvec(to_local, pa - pb)
    rot = spatial.mm(to_local, rot_a)
    rb = rbound(shape, sa) + margin
    vert, vert_valid, tri, normal, valid = _grid(sys, geom_b, local, rb, wy, wx)
    out = []
    if shape in ("sphere", "capsule"):
        if shape == "sphere":
            centres = local.unsqueeze(-2)
        else:
            half = rot[:, 2] * sa[1]
            centres = torch.stack([local - half + 2 * t * half for t in _CAPSULE_POINTS], -2)
        out.append(_deepest_triangles(centres.unsqueeze(-2), sa[0].view(-1, 1, 1, 1), tri, normal, valid,
                                      4 if shape == "sphere" else 2))
    elif shape == "box":
        corners = box_corners(local, rot, sa)  # (3, P, 8, B)
        out.append(_deepest_triangles(corners.unsqueeze(-2), 0.0, tri, normal, valid, 1))
    else:
        up = torch.zeros_like(local)
        up[2] = 1.0
        if shape == "cylinder":  # the rim points, as on a plane with the field's normal
            rim = collision_round.plane_points("cylinder", local, rot, sa, up)
            out.append(_deepest_triangles(rim.unsqueeze(-2), 0.0, tri, normal, valid, 1))
        support = local.unsqueeze(-2).unsqueeze(-2) + collision_round.offset(
            shape, rot.unsqueeze(-2).unsqueeze(-2), sa.unsqueeze(-2).unsqueeze(-2), -normal)  # (3, P, 1, T, B)
        out.append(_deepest_triangles(support, 0.0, tri, normal, valid, 4 if shape == "ellipsoid" else 2))
    if shape in ("box", "ellipsoid", "cylinder"):  # the grid's vertices inside the geom
        if shape == "box":
            pt, n, d = point_box(vert, 0.0, local.unsqueeze(-2), rot.unsqueeze(-2), sa.unsqueeze(-2))
        else:
            pt, n, d = collision_round.point_round(shape, vert, 0.0, local.unsqueeze(-2), rot.unsqueeze(-2),
                                                   sa.unsqueeze(-2))
        d = torch.where(vert_valid, d, PADDING_DISTANCE)
        out.append(_deepest(pt.unsqueeze(-3), -n.unsqueeze(-3), d.unsqueeze(-3), 4 if shape == "box" else 2, -2))
    pt, n, d = (torch.cat(x, -2) for x in zip(*out))
    rot_b = rot_b.unsqueeze(-2)
    return pb.unsqueeze(-2) + spatial.matvec(rot_b, pt), spatial.matvec(rot_b, n), d
