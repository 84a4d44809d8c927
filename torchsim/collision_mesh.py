"""Contact geometry of mesh geoms, as their convex hulls (``torchsim.collision`` dispatches here).

A hull is its vertices, each vertex's edges and its face planes in the geom frame (``System.geom_hull_vert``,
``geom_hull_edge``, ``geom_hull_plane``, from MuJoCo's compiled hull: ``torchsim.io_mjcf.meshes``), padded to the
model's largest hull; padded vertices are masked (``geom_hull_real``: their distance is set far apart, so they never
touch). The work is static and branch-free: every pair tests every (padded) vertex, face plane and axis.

The distance of a point from a hull is taken as its largest face-plane distance, ``max_f (n_f . x - d_f)``, and
the normal as that face's (an even blend of the faces that tie). Inside the hull this is exact (the nearest face).
Outside it is exact only where the point's nearest hull feature is a face; nearer an edge or vertex it is less than
the true distance (the distance to the face's plane, not to the face), down to 0 (a contact reported touching)
where a point lies just past a sharp corner: a pair may report a contact early near an edge or corner, never miss
one. ``tests/test_mesh_contacts.py`` measures it against MuJoCo's ``mj_geomDistance``.

Pairs (``a`` the lower-ranked geom, normals from ``b`` towards ``a``; ``V`` the model's largest hull's vertices):
- mesh-plane: every hull vertex against the plane, exact (``V`` points);
- sphere-mesh: the centre against the faces, minus the radius (1 point);
- capsule-mesh: spheres at both ends of the segment and at its point deepest against the faces, found by
  ``SEGMENT_ITERATIONS`` bisections on the slope of the (convex) face distance along the segment (3 points);
- box-mesh: the box's 8 corners against the hull's faces, the hull's vertices against the box (exact distance,
  ``collision._point_box``) and the separating-axis contact (:func:`_separation`) (``9 + V`` points);
- mesh-mesh: each hull's vertices against the other's faces, and the separating-axis contact (``1 + 2 V``);
- cylinder-mesh: the cylinder's 8 cap rim points against the hull's faces, the hull's vertices against the
  cylinder and a separating-axis contact (hull face normals, the cylinder's axis and its cross products with the
  edges at the hull's support vertex) (``9 + V``, :func:`_cylinder_hull`), never too shallow;
- ellipsoid-mesh: one separating-axis contact (1 point, as ellipsoid-box), over the hull's face normals and the
  ellipsoid's normals nearest each hull vertex and each edge at the vertex nearest it (:func:`_ellipsoid_hull`),
  never too shallow.
The vertices alone miss edge-edge crossings (no vertex of either inside the other); the separating-axis contact
finds them, over the face normals and the cross products of the edges at the support vertices
(``EDGE_ROUNDS`` rounds), never too shallow.
"""

import torch

from torchsim import collision_round, lanes, spatial

SEGMENT_ITERATIONS = 10
EDGE_ROUNDS = 2  #: rounds of edge-pair axes, each at the support vertices along the best axis so far
TIE_BREAK = 1e-12  # [m] per vertex index, far below any distance that matters
#: The distance [m] given to padded hull vertices: far apart, so they never touch (depth = margin - distance < 0).
PADDING_DISTANCE = 1.0


def hull_vertices(pos, rot, vert):
    """World hull vertices ``(3, P, V, B)`` of geoms at ``pos (3, P, B)``, ``rot (3, 3, P, B)`` with geom-frame
    vertices ``vert (3, P, V, 1)``."""
    return pos.unsqueeze(-2) + spatial.matvec(rot.unsqueeze(-2), vert)


def point_hull(x, pos, rot, plane):
    """Points ``x (3, P, K, B)`` against hulls at ``pos (3, P, B)``, ``rot (3, 3, P, B)`` with face planes
    ``plane (4, P, F, 1)`` (outward unit normal, offset; geom frame): (normal hull->point ``(3, P, K, B)``,
    distance ``(P, K, B)``), the largest face-plane distance and its face's normal (module docstring)."""
    local = spatial.matvec(spatial.transpose(rot).unsqueeze(-2), x - pos.unsqueeze(-2)).unsqueeze(-2)
    normal, offset = plane[:3].unsqueeze(-3), plane[3].unsqueeze(-3)  # (3, P, 1, F, 1), (P, 1, F, 1)
    face_dist = spatial.dot(local, normal) - offset  # (P, K, F, B)
    dist = face_dist.amax(-2)
    # the face that gives the maximum, without an argmax (row graphs have none): ties blend evenly
    nearest = (face_dist == dist.unsqueeze(-2)).to(x.dtype)
    n_local = spatial.normalize((normal * nearest).sum(-2))
    return spatial.matvec(rot.unsqueeze(-2), n_local), dist


def _deepest_on_segment(p0, p1, pos, rot, plane):
    """The point of each segment ``p0-p1 (3, P, B)`` whose face distance from the hull is least: that distance is
    convex along the segment (a maximum of linear functions), so bisections on the sign of its slope (the face
    normal along the segment) leave ``t`` within ``2^-(SEGMENT_ITERATIONS + 1)`` of the minimiser."""
    d = p1 - p0
    lo, width = 0.0, 1.0
    for _ in range(SEGMENT_ITERATIONS):
        width = 0.5 * width
        normal, _ = point_hull((p0 + (lo + width) * d).unsqueeze(-2), pos, rot, plane)
        # on from the midpoint where the distance still falls there (a product, not a where of two numbers,
        # which a row graph's generated code cannot hold)
        lo = lo + width * (spatial.dot(normal.select(-2, 0), d) <= 0).to(d.dtype)
    return p0 + (lo + 0.5 * width) * d


def _against_hull(x, radius, pos, rot, plane):
    """Spheres of ``radius`` at ``x (3, P, K, B)`` against hulls: (point, normal hull->sphere, distance)."""
    normal, dist = point_hull(x, pos, rot, plane)
    dist = dist - radius
    return x - normal * (radius + 0.5 * dist), normal, dist


def _masked(dist, real):
    """Distances ``(P, K, B)`` with the padded vertices' (``real (P, K, 1)`` false) set far apart."""
    return torch.where(real, dist, PADDING_DISTANCE)


def hulls(sys, geoms):
    """The hulls of ``geoms (P,)`` in lanes: vertices ``(3, P, V, 1)``, their mask ``(P, V, 1)``, the edges from
    each vertex ``(3, P, V, D, 1)`` and face planes ``(4, P, F, 1)``."""
    return (lanes.param(sys.geom_hull_vert, 2, 1).index_select(-3, geoms),
            lanes.param(sys.geom_hull_real, 2).index_select(-3, geoms),
            lanes.param(sys.geom_hull_edge, 3, 1).index_select(-4, geoms),
            lanes.param(sys.geom_hull_plane, 2, 1).index_select(-3, geoms))


def pair_contacts(kind, pa, rot_a, sa, hull_a, pb, rot_b, sb, hull_b, box_corners, point_box):
    """Contacts of one mesh pair kind (module docstring) for world geom poses ``(3, P, B)``, ``(3, 3, P, B)``, sizes
    ``(3, P, 1)`` and :func:`hulls` (a non-mesh side's unused); ``box_corners``, ``point_box``: the box helpers of
    ``torchsim.collision``. Returns point, normal ``(3, P, K, B)`` and distance ``(P, K, B)``."""
    if kind == "mesh_plane":
        vert_a, real_a, _, _ = hull_a
        pts, normal = hull_vertices(pa, rot_a, vert_a), rot_b[:, -1].unsqueeze(-2)  # the plane's z axis
        dist = spatial.dot(pts - pb.unsqueeze(-2), normal)
        return pts - 0.5 * normal * dist, normal.expand_as(pts), _masked(dist, real_a)
    if kind == "sphere_mesh":
        return _against_hull(pa.unsqueeze(-2), sa[0].unsqueeze(-2), pb, rot_b, hull_b[3])
    if kind == "capsule_mesh":
        half = rot_a[:, -1] * sa[1]
        p0, p1 = pa - half, pa + half
        deepest = _deepest_on_segment(p0, p1, pb, rot_b, hull_b[3])
        return _against_hull(torch.stack((p0, p1, deepest), -2), sa[0].unsqueeze(-2), pb, rot_b, hull_b[3])
    vert_b, real_b, edge_b, plane_b = hull_b
    side_b = _world_hull(pb, rot_b, vert_b, real_b, edge_b, plane_b)
    if kind == "ellipsoid_mesh":
        return _ellipsoid_hull(pa, rot_a, sa, side_b)
    if kind == "cylinder_mesh":
        return _cylinder_hull(pa, rot_a, sa, side_b, real_b, pb, rot_b, plane_b)
    if kind == "box_mesh":
        axes = rot_a.movedim(1, -2)  # (3, P, 3, B): the box's edge directions, the same at every corner
        side_a = (box_corners(pa, rot_a, sa), 1.0, axes.unsqueeze(-3), torch.cat((axes, -axes), -2))
        pt_a, n_a, d_a = _against_hull(side_a[0], 0.0, pb, rot_b, plane_b)
        pt_b, n_b, d_b = point_box(side_b[0], 0.0, pa.unsqueeze(-2), rot_a.unsqueeze(-2), sa.unsqueeze(-2))
    else:  # mesh_mesh
        vert_a, real_a, edge_a, plane_a = hull_a
        side_a = _world_hull(pa, rot_a, vert_a, real_a, edge_a, plane_a)
        pt_a, n_a, d_a = _against_hull(side_a[0], 0.0, pb, rot_b, plane_b)
        d_a = _masked(d_a, real_a)
        pt_b, n_b, d_b = _against_hull(side_b[0], 0.0, pa, rot_a, plane_a)
    pt_s, n_s, d_s = _separation(side_a, side_b)
    return (torch.cat((pt_a, pt_b, pt_s), -2), torch.cat((n_a, -n_b, n_s), -2),
            torch.cat((d_a, _masked(d_b, real_b), d_s), -2))


def _cylinder_hull(pa, rot_a, sa, side_b, real_b, pb, rot_b, plane_b):
    """A cylinder ``a`` against a hull ``b``: its caps' rim points against the hull's faces, 4 per cap at quarter
    turns from its deepest along the hull face normal that separates them most (as on a plane: a cylinder rests on
    a face on its cap or its side), the hull's vertices against the cylinder (exact), and a separating-axis
    contact (:func:`_cylinder_separation`) for a hull edge across the cylinder's side."""
    verts_b, _, edges_b, faces_b = side_b
    normal, sep = _round_axis("cylinder", pa, rot_a, sa, verts_b, faces_b)
    pt_a, n_a, d_a = _against_hull(collision_round.plane_points("cylinder", pa, rot_a, sa, normal), 0.0, pb, rot_b,
                                   plane_b)
    pt_b, n_b, d_b = collision_round.point_cylinder(verts_b, 0.0, pa.unsqueeze(-2), rot_a.unsqueeze(-2),
                                                    sa.unsqueeze(-2))
    pt_s, n_s, d_s = _cylinder_separation(pa, rot_a, sa, side_b, real_b, normal, sep)
    return (torch.cat((pt_a, pt_b, pt_s), -2), torch.cat((n_a, -n_b, n_s), -2),
            torch.cat((d_a, _masked(d_b, real_b), d_s), -2))


def _round_axis(shape, pa, rot_a, sa, verts_b, axes):
    """The axis of ``axes (3, P, N, B)`` (unit, hull b towards a) that separates a cylinder or ellipsoid ``a`` and a
    hull most (an even blend where axes tie), and that separation ``(P, B)``: a's lowest point along an axis is the
    deepest of the points ``collision_round.plane_points`` gives (a cylinder's 8 cap rim points, an ellipsoid's
    support point)."""
    rims = collision_round.plane_points(shape, pa.unsqueeze(-2), rot_a.unsqueeze(-2), sa.unsqueeze(-2), axes)
    sep = (spatial.dot(rims, axes.unsqueeze(-2)).amin(-2)
           - spatial.dot(verts_b.unsqueeze(-3), axes.unsqueeze(-2)).amax(-2))  # (P, N, B)
    best = sep.amax(-2)
    chosen = (sep == best.unsqueeze(-2)).to(sep.dtype)
    return spatial.normalize((axes * chosen).sum(-2)), best


def _cylinder_separation(pa, rot_a, sa, side_b, real_b, face_normal, face_sep):
    """A cylinder's separating-axis contact with a hull (point, normal b->a ``(3, P, 1, B)``, distance
    ``(P, 1, B)``): the best hull face normal's separation (``face_normal``, ``face_sep``), or a better one across
    the cylinder's axis and an edge at the hull's support vertex along it (a hull edge across the side), or along
    the axis: every separation is a lower bound on the signed distance, so never too shallow. The point is midway
    across the gap from the cylinder's deepest rim point (a face's normal) or between the two support points."""
    verts_b, _, edges_b, _ = side_b
    axis = rot_a[:, 2]
    edge_b = (edges_b * _extreme(verts_b, real_b.to(verts_b.dtype), face_normal, 1.0, one=True).unsqueeze(-2)
              ).sum(-3)  # (3, P, D, B)
    cross = spatial.cross(edge_b, axis.unsqueeze(-2))
    square = spatial.dot(cross, cross)
    parallel = square <= 1e-6 * spatial.dot(edge_b, edge_b)  # along the axis: no axis, the face normal instead
    cross = torch.where(parallel, face_normal.unsqueeze(-2), cross * torch.rsqrt(square.clamp_min(1e-30)))
    axes = torch.cat((cross, -cross, axis.unsqueeze(-2), -axis.unsqueeze(-2)), -2)
    edge_normal, edge_sep = _round_axis("cylinder", pa, rot_a, sa, verts_b, axes)
    across = edge_sep > face_sep
    normal, sep = torch.where(across, edge_normal, face_normal), torch.maximum(edge_sep, face_sep)
    rim = collision_round.plane_points("cylinder", pa, rot_a, sa, normal)  # (3, P, 8, B)
    along = spatial.dot(rim, normal.unsqueeze(-2))
    deepest = (along == along.amin(-2, keepdim=True)).to(along.dtype)
    low_a = (rim * deepest).sum(-2) / deepest.sum(-2)
    high_b = (verts_b * _extreme(verts_b, real_b.to(verts_b.dtype), normal, 1.0)).sum(-2)
    point = torch.where(across, 0.5 * (low_a + high_b), low_a - 0.5 * sep * normal)
    return point.unsqueeze(-2), normal.unsqueeze(-2), sep.unsqueeze(-2)


def _ellipsoid_hull(pa, rot_a, sa, side_b):
    """An ellipsoid ``a`` against a hull ``b`` (:func:`_world_hull`): one separating-axis contact (point, normal
    b->a ``(3, P, 1, B)``, distance ``(P, 1, B)``), the best of three sets of axes. The hull's face normals: exact
    where the ellipsoid's nearest point (or deepest) is over a face. The ellipsoid's normals at its points nearest
    each hull vertex (``collision_round.point_ellipsoid``): exact where a vertex is the hull's nearest feature.
    Then the ellipsoid's normals at its points nearest the edges at the hull vertex nearest it (each edge's point
    nearest the ellipsoid, ``collision_round.segment_point``), squared to the edge: exact where that edge is the
    nearest feature. Every axis's separation is a lower bound on the signed distance, so the contact is never too
    shallow; elsewhere (the nearest feature an edge not at that vertex, or deep inside, where the normal at a
    nearest point is not the shallowest way out) it errs deep. The point is midway across the gap from the
    ellipsoid's support point along the normal, as on a plane."""
    verts_b, real_b, edges_b, faces_b = side_b
    ellipsoid = pa.unsqueeze(-2), rot_a.unsqueeze(-2), sa.unsqueeze(-2)
    _, vert_normal, vert_dist = collision_round.point_ellipsoid(verts_b, 0.0, *ellipsoid)  # ellipsoid -> vertex
    normal, sep = _round_axis("ellipsoid", pa, rot_a, sa, verts_b, torch.cat((faces_b, -vert_normal), -2))
    support = _largest(-vert_dist, real_b, one=True)  # (P, V, B)
    start = (verts_b * support).sum(-2).unsqueeze(-2)  # (3, P, 1, B)
    edges = (edges_b * support.unsqueeze(-2)).sum(-3)  # (3, P, D, B)
    nearest = collision_round.segment_point("ellipsoid", start.expand_as(edges), start + edges, *ellipsoid)
    _, edge_normal, _ = collision_round.point_ellipsoid(nearest, 0.0, *ellipsoid)
    # square to the edge: the bisection leaves the point off by up to 2^-11 of the edge, which tilts the normal, and
    # a tilted axis would lose the edge's half length times the tilt
    along = edges * torch.rsqrt(spatial.dot(edges, edges).clamp_min(1e-30))  # a zero edge (none): zero
    square = edge_normal - spatial.dot(edge_normal, along) * along
    length = spatial.safe_norm(square)
    edge_normal = torch.where(length > 1e-6, square / length, edge_normal)  # along the edge: no square axis
    edge_normal, edge_sep = _round_axis("ellipsoid", pa, rot_a, sa, verts_b, -edge_normal)
    normal = torch.where(edge_sep > sep, edge_normal, normal)
    sep = torch.maximum(edge_sep, sep)
    point = pa - collision_round.offset("ellipsoid", rot_a, sa, normal) - 0.5 * sep * normal
    return point.unsqueeze(-2), normal.unsqueeze(-2), sep.unsqueeze(-2)


def _world_hull(pos, rot, vert, real, edge, plane):
    """A hull in the world for :func:`_separation`: vertices ``(3, P, V, B)``, 1 where a vertex is real and 0 at
    padding ``(P, V, 1)``, each vertex's edges ``(3, P, V, D, B)`` and the outward face normals ``(3, P, F, B)``."""
    return (hull_vertices(pos, rot, vert), real.to(vert.dtype), spatial.matvec(rot[..., None, None, :], edge),
            spatial.matvec(rot.unsqueeze(-2), plane[:3]))


def _separation(side_a, side_b):
    """The separating-axis test as one contact (point, normal b->a ``(3, P, 1, B)``, distance ``(P, 1, B)``) for
    hulls (or a box) ``side_a``, ``side_b`` (:func:`_world_hull`). The separation ``sep(n) = min_a a.n - max_b b.n``
    is a lower bound on the signed distance for every unit ``n``, so its maximum over some axes finds every
    overlap, edge-edge crossings too, never too shallow. The axes: both hulls' face normals, then the cross
    products of the edges at the two support vertices along the best of those (both ways), where an edge-edge
    contact lies. Exact where the deepest overlap (or the gap) is along a face normal or such an edge pair's;
    short (too deep, or touching early) by the gap to an edge pair elsewhere. The point is midway across the gap
    from the support point of the side whose face gave the normal, or between the two support points for an edge
    pair's (an even blend where axes tie)."""
    (verts_a, real_a, edges_a, faces_a), (verts_b, real_b, edges_b, faces_b) = side_a, side_b
    faces = torch.cat((-faces_a, faces_b), -2)  # (3, P, Fa + Fb, B), each from b towards a
    normal, best, chosen = _best_axis(verts_a, verts_b, faces)
    share_a, share_b = chosen.split([faces_a.shape[-2], faces_b.shape[-2]], -2)  # the faces' shares in the normal
    share_a, share_b = share_a.sum(-2), share_b.sum(-2)
    for _ in range(EDGE_ROUNDS):
        edge_a = (edges_a * _extreme(verts_a, real_a, normal, -1.0, one=True).unsqueeze(-2)).sum(-3)  # (3, P, D, B)
        edge_b = (edges_b * _extreme(verts_b, real_b, normal, 1.0, one=True).unsqueeze(-2)).sum(-3)
        cross = spatial.cross(edge_a.unsqueeze(-2), edge_b.unsqueeze(-3)).flatten(-3, -2)  # (3, P, Da Db, B)
        square = spatial.dot(cross, cross)
        # nearly parallel edges (within 1e-3 rad) give no axis: the normal so far instead (every axis must be unit)
        parallel = square <= 1e-6 * (spatial.dot(edge_a, edge_a).amax(-2) * spatial.dot(edge_b, edge_b).amax(-2)
                                     ).unsqueeze(-2)
        cross = torch.where(parallel, normal.unsqueeze(-2), cross * torch.rsqrt(square.clamp_min(1e-30)))
        edge_normal, edge_best, _ = _best_axis(verts_a, verts_b, torch.cat((cross, -cross), -2))
        better = edge_best > best
        normal = torch.where(better, edge_normal, normal)
        share_a, share_b = (torch.where(better, 0.0, share) for share in (share_a, share_b))
        best = torch.maximum(edge_best, best)
    low_a = (verts_a * _extreme(verts_a, real_a, normal, -1.0)).sum(-2)
    high_b = (verts_b * _extreme(verts_b, real_b, normal, 1.0)).sum(-2)
    best = spatial.dot(low_a - high_b, normal)  # of the blended normal where axes tie
    point = (share_b * (low_a - 0.5 * best * normal) + share_a * (high_b + 0.5 * best * normal)
             + (1 - share_a - share_b) * 0.5 * (low_a + high_b))
    return point.unsqueeze(-2), normal.unsqueeze(-2), best.unsqueeze(-2)


def _best_axis(verts_a, verts_b, axes):
    """The axis of ``axes (3, P, N, B)`` (unit, b towards a) with the largest ``sep`` (an even blend where axes
    tie), that ``sep (P, B)`` and each axis's share in the axis ``(P, N, B)``."""
    sep = (spatial.dot(verts_a.unsqueeze(-3), axes.unsqueeze(-2)).amin(-2)  # padding repeats a vertex: no change
           - spatial.dot(verts_b.unsqueeze(-3), axes.unsqueeze(-2)).amax(-2))
    best = sep.amax(-2)
    chosen = (sep == best.unsqueeze(-2)).to(sep.dtype)
    chosen = chosen / chosen.sum(-2, keepdim=True)
    return spatial.normalize((axes * chosen).sum(-2)), best, chosen


def _extreme(verts, real, normal, side, one=False):
    """Weights ``(P, V, B)`` summing to 1 over the (real) vertices ``(3, P, V, B)`` farthest along
    ``side * normal (3, P, B)``: an even blend of tied vertices, or with ``one`` the first of them (ties broken by
    ``TIE_BREAK`` per vertex index: a blend of two vertices' edges would be no edge)."""
    return _largest(side * spatial.dot(verts, normal.unsqueeze(-2)), real, one)


def _largest(score, real, one=False):
    """Weights ``(P, V, B)`` summing to 1 over the (real) vertices with the largest ``score (P, V, B)``: an even blend
    of ties, or with ``one`` the first of them (:func:`_extreme`)."""
    if one:
        score = score - TIE_BREAK * torch.arange(score.shape[-2], dtype=score.dtype, device=score.device).unsqueeze(-1)
    weight = (score == score.amax(-2, keepdim=True)).to(score.dtype) * real
    return weight / weight.sum(-2, keepdim=True)
