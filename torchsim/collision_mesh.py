"""Contact geometry of mesh geoms, as their convex hulls (``torchsim.collision`` dispatches here).

A hull is its vertices and face planes in the geom frame (``System.geom_hull_vert``, ``geom_hull_plane``, from
MuJoCo's compiled hull: ``torchsim.io_mjcf.meshes``), padded to the model's largest hull; padded vertices are
masked (``hull_real``: their distance is set far apart, so they never touch). The work is static and branch-free:
every pair tests every (padded) vertex and face plane.

The distance of a point from a hull is taken as its largest face-plane distance, ``max_f (n_f . x - d_f)``, and
the normal as that face's (an even blend of the faces that tie). Inside the hull this is exact (the nearest face).
Outside it is exact only where the point's nearest hull feature is a face; nearer an edge or vertex it is less than
the true distance (the distance to the face's plane, not to the face): down to ``cos`` of half the angle between
the adjoining faces' normals times the true distance in the plane across an edge, and to 0 (a contact reported
touching) where a point lies just past a vertex at a sharp corner. With margin 0 only the face planes' distances
matter where the geoms touch, so a pair may report a contact up to that gap early near a sharp edge or corner,
never miss one (module ``test_mesh_contacts`` measures it).

Pairs (``a`` the lower-ranked geom, normals from ``b`` towards ``a``; ``V`` the model's largest hull's vertices):
- mesh-plane: every hull vertex against the plane, exact (``V`` points);
- sphere-mesh: the centre against the faces, minus the radius (1 point);
- capsule-mesh: spheres at both ends of the segment and at its point deepest against the faces, found by
  ``SEGMENT_ITERATIONS`` bisections on the slope of the (convex) face distance along the segment (3 points);
- box-mesh: the box's 8 corners against the hull's faces, and the hull's vertices against the box (exact distance,
  ``collision._point_box``) (``8 + V`` points);
- mesh-mesh: each hull's vertices against the other's faces (``2 V`` points).
Box-mesh and mesh-mesh test vertices against faces only, so edge-edge crossings (two hulls whose edges cross with
no vertex of either inside the other) are missed, as box-box misses them.
"""

import torch

from torchsim import lanes, spatial

SEGMENT_ITERATIONS = 10
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
    """The hulls of ``geoms (P,)`` in lanes: vertices ``(3, P, V, 1)``, their mask ``(P, V, 1)`` and face planes
    ``(4, P, F, 1)``."""
    return (lanes.param(sys.geom_hull_vert, 2, 1).index_select(-3, geoms),
            lanes.param(sys.geom_hull_real, 2).index_select(-3, geoms),
            lanes.param(sys.geom_hull_plane, 2, 1).index_select(-3, geoms))


def pair_contacts(kind, pa, rot_a, sa, hull_a, pb, rot_b, sb, hull_b, box_corners, point_box):
    """Contacts of one mesh pair kind (module docstring) for world geom poses ``(3, P, B)``, ``(3, 3, P, B)``, sizes
    ``(3, P, 1)`` and :func:`hulls` (a non-mesh side's unused); ``box_corners``, ``point_box``: the box helpers of
    ``torchsim.collision``. Returns point, normal ``(3, P, K, B)`` and distance ``(P, K, B)``."""
    if kind == "mesh_plane":
        vert_a, real_a, _ = hull_a
        pts, normal = hull_vertices(pa, rot_a, vert_a), rot_b[:, -1].unsqueeze(-2)  # the plane's z axis
        dist = spatial.dot(pts - pb.unsqueeze(-2), normal)
        return pts - 0.5 * normal * dist, normal.expand_as(pts), _masked(dist, real_a)
    if kind == "sphere_mesh":
        return _against_hull(pa.unsqueeze(-2), sa[0].unsqueeze(-2), pb, rot_b, hull_b[2])
    if kind == "capsule_mesh":
        half = rot_a[:, -1] * sa[1]
        p0, p1 = pa - half, pa + half
        deepest = _deepest_on_segment(p0, p1, pb, rot_b, hull_b[2])
        return _against_hull(torch.stack((p0, p1, deepest), -2), sa[0].unsqueeze(-2), pb, rot_b, hull_b[2])
    vert_b, real_b, plane_b = hull_b
    verts_b = hull_vertices(pb, rot_b, vert_b)
    if kind == "box_mesh":
        pt_a, n_a, d_a = _against_hull(box_corners(pa, rot_a, sa), 0.0, pb, rot_b, plane_b)
        pt_b, n_b, d_b = point_box(verts_b, 0.0, pa.unsqueeze(-2), rot_a.unsqueeze(-2), sa.unsqueeze(-2))
    else:  # mesh_mesh
        vert_a, real_a, plane_a = hull_a
        pt_a, n_a, d_a = _against_hull(hull_vertices(pa, rot_a, vert_a), 0.0, pb, rot_b, plane_b)
        d_a = _masked(d_a, real_a)
        pt_b, n_b, d_b = _against_hull(verts_b, 0.0, pa, rot_a, plane_a)
    return torch.cat((pt_a, pt_b), -2), torch.cat((n_a, -n_b), -2), torch.cat((d_a, _masked(d_b, real_b)), -2)
