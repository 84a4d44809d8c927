"""Contact geometry: candidate geom pairs (fixed at load) -> contact points, normals and penetration depths.

Each shape pair has a fixed number of contact points (a box on a plane tests its 8 corners), so the contact
count is static and activity is a mask, never control flow. Geom ``a`` is the lower-ranked shape of a pair
(sphere < capsule < ellipsoid < cylinder < box < mesh < plane < hfield); normals point from ``b`` towards ``a``.
Pairs with an ellipsoid or a cylinder are computed in ``torchsim.collision_round``, pairs with a mesh (its convex
hull) in ``torchsim.collision_mesh``, pairs with a height field in ``torchsim.collision_hfield``; each module gives
their accuracy.

A geom is posed by the frame it moves with (``System.geom_frame``): its body's, or a mocap body's per-env
``mocap_pos``/``mocap_quat`` (read only where a pair has a mocap geom, ``System.contact_mocap``); a mocap geom's side
is the world's, at rest and taking no impulse, as MuJoCo's mocap bodies are.

Tensors are in the lanes layout (``torchsim.lanes``). A group's ``P`` pairs with ``K`` points each are evaluated as
``(*C, P, K, B)``, the point axis at ``-2`` as every entity axis inserted before the batch, and flattened to the
group's ``P K`` contacts at the end.

Approximations (exact pairs are plane-*, sphere-sphere, sphere-capsule, capsule-capsule, sphere-box):
- capsule-box tests three spheres of the capsule's segment (both ends and the point nearest the box centre);
- box-box tests each box's 8 corners against the other box, so edge-edge crossings are missed.
"""

from typing import NamedTuple

import torch

from torchsim import collision_hfield, collision_mesh, collision_round, lanes, spatial, welds
from torchsim.kinematics import Bodies
from torchsim.system import System

SHAPE_RANK = {"sphere": 0, "capsule": 1, "ellipsoid": 2, "cylinder": 3, "box": 4, "mesh": 5, "plane": 6, "hfield": 7}
# unit box corners (3, 1, 8, 1): components, then broadcast over pairs, the 8 corners, broadcast over the batch
_CORNERS = torch.tensor([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)],
                        dtype=torch.float64).T[:, None, :, None]
#: the 12 edges of a box as pairs of ``_CORNERS`` (first ends, then second ends): corners differing in one sign
_EDGES = torch.tensor([[i, i | bit] for bit in (4, 2, 1) for i in range(8) if not i & bit]).T


class Contacts(NamedTuple):
    """Contact points of all pairs, ``C`` per env.

    Attributes:
        pos: (3, C, B) world contact point (midway between the surfaces) [m].
        normal: (3, C, B) unit normal from body b towards body a.
        depth: (C, B) penetration (margin - distance) [m]; the contact is active where depth > 0.
        body_a, body_b: (C,) ext body indices; ``body_b`` is None where every pair is a plane pair (planes
            belong to the static world; ``torchsim.rigid`` then skips the world's side).
        friction: (C, 1) or, per env, (C, B).
        tangent: (3, C, B) the direction MuJoCo's contact frame takes its first tangent from (``mjContact.frame``
            before ``mju_makeFrame``): a capsule's axis where it touches a plane, else 0 (world y, or z). A pyramidal
            friction cone's edges lie along the frame's tangents, so a sliding foot's friction depends on it.
    """

    pos: torch.Tensor
    normal: torch.Tensor
    depth: torch.Tensor
    body_a: torch.Tensor
    body_b: torch.Tensor | None
    friction: torch.Tensor
    tangent: torch.Tensor


def _segment(pos, rot, size):
    """End points of a capsule's axis segment (local z, the frame's last column; half-length ``size[1]``)."""
    half = rot[:, -1] * size[1]
    return pos - half, pos + half


def _closest_on_segment(p0, p1, x):
    d = p1 - p0
    t = torch.clamp(spatial.dot(x - p0, d) / spatial.dot(d, d).clamp_min(1e-12), 0.0, 1.0)
    return p0 + t * d


def _segments_closest(p0, p1, q0, q1):
    """Closest points between segments p0-p1 and q0-q1 (clamped parametric solution, branch-free)."""
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a, e, f = spatial.dot(d1, d1), spatial.dot(d2, d2), spatial.dot(d2, r)
    c, b = spatial.dot(d1, r), spatial.dot(d1, d2)
    denom = (a * e - b * b).clamp_min(1e-12)
    s = torch.clamp((b * f - c * e) / denom, 0.0, 1.0)
    t = torch.clamp((b * s + f) / e.clamp_min(1e-12), 0.0, 1.0)
    s = torch.clamp((b * t - c) / a.clamp_min(1e-12), 0.0, 1.0)
    return p0 + s * d1, q0 + t * d2


def _sphere_sphere(ca, ra, cb, rb):
    """Two spheres (also capsule segment points): (point, normal b->a, distance)."""
    d = ca - cb
    dist = spatial.safe_norm(d)
    normal = d / dist
    midpoint = 0.5 * ((ca - normal * ra) + (cb + normal * rb))
    return midpoint, normal, dist - ra - rb


def _point_box(x, r, box_pos, box_rot, half):
    """Sphere of radius ``r`` at ``x`` against a box: (point, normal box->sphere, distance); exact inside and out."""
    local = spatial.matvec(spatial.transpose(box_rot), x - box_pos)
    clamped = torch.maximum(torch.minimum(local, half), -half)
    outside_vec = local - clamped
    out_dist = spatial.safe_norm(outside_vec)
    outside = outside_vec.abs().amax(0) > 0
    # inside: leave through the nearest face
    face_gap = half - local.abs()
    gap_x, gap_y, gap_z = face_gap.unbind(0)  # the first smallest, as argmin picks, without a gather
    nearest_x = (gap_x <= gap_y) & (gap_x <= gap_z)
    nearest_y = ~nearest_x & (gap_y <= gap_z)
    axis = torch.stack([nearest_x, nearest_y, ~(nearest_x | nearest_y)]).to(x.dtype)
    in_normal = axis * torch.where(local >= 0, 1.0, -1.0)
    normal_local = torch.where(outside, outside_vec / out_dist, in_normal)
    dist = torch.where(outside, out_dist, -(face_gap * axis).sum(0)) - r
    normal = spatial.matvec(box_rot, normal_local)
    return x - normal * (r + 0.5 * dist), normal, dist


def _box_corners(pos, rot, size):
    """World corners ``(3, P, 8, B)`` of boxes at positions ``(3, P, B)`` and rotations ``(3, 3, P, B)`` with half
    sizes ``(3, P, 1)``."""
    corners = _CORNERS.to(pos) * size.unsqueeze(-2)
    return pos.unsqueeze(-2) + spatial.matvec(rot.unsqueeze(-2), corners)


def _round_box(shape, pa, rot_a, sa, pb, rot_b, sb):
    """Contacts of ellipsoids or cylinders ``a`` with boxes ``b`` (``collision_round`` gives the other pairs of the
    round shapes), for poses ``(3, P, B)``, ``(3, 3, P, B)`` and sizes ``(3, P, 1)``.

    The separating normal ``n*`` (``collision_round.separating_normal``) is climbed from the best of the box's face
    normals, the centre line, the box's normal nearest a's centre, a's nearest the box's centre and, for a cylinder, its
    axis and the normals to it and each box edge: its separation is the first contact (a lower bound on the signed
    distance, so it errs deep, never missed; MuJoCo's convex solver finds that maximum), between a's support point
    along ``-n*`` and the box. An ellipsoid has that one point, as on a plane. A cylinder adds its caps' 4 rim points
    at quarter turns from the deepest along ``-n*`` (as on a plane) against the box, and the box's 8 corners and
    the point of each of its 12 edges nearest the cylinder or deepest in it (``collision_round.segment_point``)
    against the cylinder: exact outside the other geom, inside it measured below its support plane along ``n*``.
    So a cylinder rests on a cap, its side or a rim, also where a box edge crosses its cap (a cylinder standing
    half over the edge: the edge's point under the cap closes the support polygon around its centre), and a box
    rests on a cylinder's cap (29 points)."""
    a, b = (shape, pa, rot_a, sa), ("box", pb, rot_b, sb)
    box_normal = _point_box(pa, 0.0, pb, rot_b, sb)[1]
    own_normal = collision_round.point_round(shape, pb, 0.0, pa, rot_a, sa)[1]  # a's, towards the box's centre
    cands = [rot_b[:, 0], rot_b[:, 1], rot_b[:, 2], pa - pb, box_normal, -own_normal]
    if shape == "cylinder":
        cands += [rot_a[:, 2]] + [spatial.cross(rot_a[:, 2], rot_b[:, k]) for k in range(3)]
    pt_sep, n_sep, d_sep = collision_round.separation_contact(torch.stack(cands, -2), a, b, climb_best_only=True)
    n_star = n_sep.select(-2, 0)
    if shape == "ellipsoid":
        return pt_sep, n_sep, d_sep
    box, cyl = ((x.unsqueeze(-2) for x in y) for y in ((pb, rot_b, sb), (pa, rot_a, sa)))
    (box_pos, box_rot, box_size), (cyl_pos, cyl_rot, cyl_size) = box, cyl
    rim = collision_round.plane_points("cylinder", pa, rot_a, sa, n_star)  # (3, P, 8, B)
    _, n_rim, d_rim = _point_box(rim, 0.0, box_pos, box_rot, box_size)  # out of the box
    inside = d_rim <= 0
    d_rim = torch.where(inside, spatial.dot(rim - box_pos, n_sep) - collision_round.width("box", box_rot, box_size,
                                                                                          n_sep), d_rim)
    n_rim = torch.where(inside, n_sep, n_rim)
    corners = _box_corners(pb, rot_b, sb)
    ends = corners.index_select(-2, _EDGES.to(corners.device).flatten()).unflatten(-2, (2, 12))
    edge_points = collision_round.segment_point("cylinder", *ends.unbind(-3), cyl_pos, cyl_rot, cyl_size)
    corners = torch.cat((corners, edge_points), -2)
    _, n_cor, d_cor = collision_round.point_cylinder(corners, 0.0, cyl_pos, cyl_rot, cyl_size)  # out of the cylinder
    inside = d_cor <= 0
    d_cor = torch.where(inside, -spatial.dot(corners - cyl_pos, n_sep) - collision_round.width(
        "cylinder", cyl_rot, cyl_size, n_sep), d_cor)
    n_cor = torch.where(inside, -n_sep, n_cor)
    return (torch.cat((rim - 0.5 * n_rim * d_rim, corners - 0.5 * n_cor * d_cor, pt_sep), -2),
            torch.cat((n_rim, -n_cor, n_sep), -2), torch.cat((d_rim, d_cor, d_sep), -2))


def _pair_contacts(kind, pa, rot_a, sa, pb, rot_b, sb):
    """Contacts of one shape pair for world geom positions ``(3, P, B)``, rotations ``rot_a, rot_b (3, 3, P, B)``
    (only their z columns, ``(3, 1, P, B)``, where the pair has no box, ellipsoid or cylinder) and sizes
    ``(3, P, 1)``; returns point ``(3, P, K, B)``, normal ``(3, P, K, B)``, distance ``(P, K, B)``."""
    if kind.endswith("_plane"):
        normal = rot_b[:, -1]  # the plane's z axis
        if kind == "sphere_plane":
            pts, radius = pa.unsqueeze(-2), sa[0].unsqueeze(-2)
        elif kind == "capsule_plane":
            pts, radius = torch.stack(_segment(pa, rot_a, sa), -2), sa[0].unsqueeze(-2)
        elif kind == "box_plane":
            pts, radius = _box_corners(pa, rot_a, sa), 0.0
        else:
            pts, radius = collision_round.plane_points(kind[:-6], pa, rot_a, sa, normal), 0.0
        normal = normal.unsqueeze(-2).expand_as(pts)
        dist = spatial.dot(pts - pb.unsqueeze(-2), normal) - radius
        return pts - normal * (radius + 0.5 * dist), normal, dist
    if kind == "ellipsoid_ellipsoid":
        return collision_round.ellipsoid_pair(pa, rot_a, sa, pb, rot_b, sb)
    if kind == "cylinder_cylinder":
        return collision_round.cylinder_pair(pa, rot_a, sa, pb, rot_b, sb)
    if kind == "ellipsoid_cylinder":
        return collision_round.ellipsoid_cylinder(pa, rot_a, sa, pb, rot_b, sb)
    if kind in ("ellipsoid_box", "cylinder_box"):
        return _round_box(kind[:-4], pa, rot_a, sa, pb, rot_b, sb)
    if kind == "box_box":
        pt_a, n_a, d_a = _point_box(_box_corners(pa, rot_a, sa), 0.0, pb.unsqueeze(-2), rot_b.unsqueeze(-2),
                                    sb.unsqueeze(-2))
        pt_b, n_b, d_b = _point_box(_box_corners(pb, rot_b, sb), 0.0, pa.unsqueeze(-2), rot_a.unsqueeze(-2),
                                    sa.unsqueeze(-2))
        return torch.cat((pt_a, pt_b), -2), torch.cat((n_a, -n_b), -2), torch.cat((d_a, d_b), -2)
    # sphere-like a (sphere, or points on a capsule's segment)
    if kind.startswith("sphere"):
        centres = pa.unsqueeze(-2)
    elif kind == "capsule_capsule":
        p0, p1 = _segment(pa, rot_a, sa)
        q0, q1 = _segment(pb, rot_b, sb)
        ca, cb = _segments_closest(p0, p1, q0, q1)
        pt, n, d = _sphere_sphere(ca, sa[0], cb, sb[0])
        return pt.unsqueeze(-2), n.unsqueeze(-2), d.unsqueeze(-2)
    else:  # capsule_box, capsule_ellipsoid, capsule_cylinder
        p0, p1 = _segment(pa, rot_a, sa)
        middle = (_closest_on_segment(p0, p1, pb) if kind == "capsule_box"
                  else collision_round.segment_point(kind[8:], p0, p1, pb, rot_b, sb))
        centres = torch.stack((p0, p1, middle), -2)
    ra = sa[0].unsqueeze(-2)
    if kind.endswith("_sphere"):
        return _sphere_sphere(centres, ra, pb.unsqueeze(-2), sb[0].unsqueeze(-2))
    if kind.endswith("_capsule"):
        q0, q1 = _segment(pb, rot_b, sb)
        nearest = _closest_on_segment(q0.unsqueeze(-2), q1.unsqueeze(-2), centres)
        return _sphere_sphere(centres, ra, nearest, sb[0].unsqueeze(-2))
    if kind.endswith("_box"):
        return _point_box(centres, ra, pb.unsqueeze(-2), rot_b.unsqueeze(-2), sb.unsqueeze(-2))
    return collision_round.point_round(kind.split("_")[1], centres, ra, pb.unsqueeze(-2), rot_b.unsqueeze(-2),
                                       sb.unsqueeze(-2))


def _on_world(group) -> bool:
    """Whether every pair of a contact group has the static world as body b: plane and height-field pairs (the
    loader puts planes and height fields on the world, whose geom frames are world frames)."""
    return group.kind.endswith(("_plane", "_hfield"))


def contacts(sys: System, bodies: Bodies, rot: torch.Tensor | None = None) -> Contacts:
    """Evaluate every candidate contact point of the model at the given ext body poses (lanes ``Bodies``);
    ``rot (3, 3, N + 1, B)``: the bodies' rotation matrices where the caller has them (default: built from
    ``bodies.x_quat``)."""
    rot = spatial.quat_to_mat(bodies.x_quat) if rot is None else rot
    x_pos = bodies.x_pos
    if sys.contact_mocap:  # the frames the geoms move with (System.geom_frame): the ext bodies', then the mocap bodies'
        mocap_pos, mocap_quat = welds.mocap_poses(sys, x_pos.shape[-1])
        x_pos = torch.cat((x_pos, mocap_pos), -2)
        rot = torch.cat((rot, spatial.quat_to_mat(mocap_quat)), -2)
    geom_pos, geom_size = lanes.param(sys.geom_pos, 1, 1), lanes.param(sys.geom_size, 1, 1)
    geom_rot = spatial.quat_to_mat(lanes.param(sys.geom_quat, 1, 1))
    pos, normal, depth, body_a, body_b, friction, tangent = [], [], [], [], [], [], []
    for group in sys.contact_groups:
        on_world = _on_world(group)
        geom = group.geom_a if on_world else torch.cat((group.geom_a, group.geom_b))  # moving sides' poses at once
        frame = sys.geom_frame[geom]
        full = any(shape in group.kind for shape in ("box", "ellipsoid", "cylinder", "mesh", "hfield"))
        frames = geom_rot if full else geom_rot[:, 2:]  # capsules and planes need only their z axes
        x, r = x_pos.index_select(-2, frame), rot.index_select(-2, frame)
        world_pos = x + spatial.matvec(r, geom_pos.index_select(-2, geom))
        world_rot = spatial.mm(r, frames.index_select(-2, geom))
        if on_world:  # the plane's pose is its geom frame: (3, P, 1), (3, 3|1, P, 1)
            pos_a, pos_b = world_pos, geom_pos.index_select(-2, group.geom_b)
            rot_a, rot_b = world_rot, frames.index_select(-2, group.geom_b)
        else:
            (pos_a, pos_b), (rot_a, rot_b) = world_pos.chunk(2, -2), world_rot.chunk(2, -2)
        size_a, size_b = geom_size.index_select(-2, torch.cat((group.geom_a, group.geom_b))).chunk(2, -2)
        if group.kind.endswith("_hfield"):
            pt, n, dist = collision_hfield.pair_contacts(sys, group.kind, group.geom_b, lanes.param(group.margin, 1),
                                                         pos_a, rot_a, size_a, pos_b, rot_b, _box_corners, _point_box)
        elif "mesh" in group.kind:
            hull_a, hull_b = collision_mesh.hulls(sys, group.geom_a), collision_mesh.hulls(sys, group.geom_b)
            pt, n, dist = collision_mesh.pair_contacts(group.kind, pos_a, rot_a, size_a, hull_a, pos_b, rot_b, size_b,
                                                       hull_b, _box_corners, _point_box)
        else:
            pt, n, dist = _pair_contacts(group.kind, pos_a, rot_a, size_a, pos_b, rot_b, size_b)
        k = pt.shape[-2]
        pos.append(pt.flatten(-3, -2))
        normal.append(n.flatten(-3, -2))
        depth.append((lanes.param(group.margin, 1).unsqueeze(-2) - dist).flatten(-3, -2))
        body_a.append(sys.geom_body[group.geom_a].repeat_interleave(k))
        body_b.append(sys.geom_body[group.geom_b].repeat_interleave(k))
        friction.append(lanes.param(group.friction, 1).repeat_interleave(k, dim=0))
        # MuJoCo aligns a capsule-plane contact's frame with the capsule's axis (mjc_PlaneCapsule)
        hint = rot_a[:, -1].unsqueeze(-2).expand_as(pt) if group.kind == "capsule_plane" else torch.zeros_like(pt)
        tangent.append(hint.flatten(-3, -2))
    if not pos:
        b = bodies.x_pos.shape[-1]
        empty = bodies.x_pos.new_zeros(3, 0, b)
        idx = sys.geom_body.new_zeros(0)
        return Contacts(empty, empty, bodies.x_pos.new_zeros(0, b), idx, idx, bodies.x_pos.new_zeros(0, 1), empty)
    return Contacts(torch.cat(pos, -2), torch.cat(normal, -2), torch.cat(depth, -2), torch.cat(body_a),
                    None if all(map(_on_world, sys.contact_groups)) else torch.cat(body_b), torch.cat(friction, -2),
                    torch.cat(tangent, -2))
