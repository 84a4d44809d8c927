"""Contact geometry: candidate geom pairs (fixed at load) -> contact points, normals and penetration depths.

Each shape pair has a fixed number of contact points (a box on a plane tests its 8 corners), so the contact
count is static and activity is a mask, never control flow. Geom ``a`` is the lower-ranked shape of a pair
(sphere < capsule < box < plane); normals point from ``b`` towards ``a``.

Approximations (exact pairs are plane-*, sphere-sphere, sphere-capsule, capsule-capsule, sphere-box):
- capsule-box tests three spheres of the capsule's segment (both ends and the point nearest the box centre);
- box-box tests each box's 8 corners against the other box, so edge-edge crossings are missed.
"""

from typing import NamedTuple

import torch

from torchsim import math
from torchsim.kinematics import Bodies
from torchsim.system import System

SHAPE_RANK = {"sphere": 0, "capsule": 1, "box": 2, "plane": 3}
POINTS_PER_PAIR = {
    "sphere_plane": 1, "capsule_plane": 2, "box_plane": 8, "sphere_sphere": 1, "sphere_capsule": 1,
    "capsule_capsule": 1, "sphere_box": 1, "capsule_box": 3, "box_box": 16,
}
_CORNERS = torch.tensor([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=torch.float64)


class Contacts(NamedTuple):
    """Contact points of all pairs, ``C`` per env.

    Attributes:
        pos: (B, C, 3) world contact point (midway between the surfaces) [m].
        normal: (B, C, 3) unit normal from body b towards body a.
        depth: (B, C) penetration (margin - distance) [m]; the contact is active where depth > 0.
        body_a, body_b: (C,) ext body indices.  friction: (C,) or (B, C).
    """

    pos: torch.Tensor
    normal: torch.Tensor
    depth: torch.Tensor
    body_a: torch.Tensor
    body_b: torch.Tensor
    friction: torch.Tensor


def _segment(pos, quat, size):
    """End points of a capsule's axis segment (local z, half-length ``size[1]``)."""
    half = math.quat_rotate(quat, torch.stack((torch.zeros_like(size[..., 1]),) * 2 + (size[..., 1],), -1))
    return pos - half, pos + half


def _closest_on_segment(p0, p1, x):
    d = p1 - p0
    t = torch.clamp(math.dot(x - p0, d) / math.dot(d, d).clamp_min(1e-12), 0.0, 1.0)
    return p0 + t * d


def _segments_closest(p0, p1, q0, q1):
    """Closest points between segments p0-p1 and q0-q1 (clamped parametric solution, branch-free)."""
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a, e, f = math.dot(d1, d1), math.dot(d2, d2), math.dot(d2, r)
    c, b = math.dot(d1, r), math.dot(d1, d2)
    denom = (a * e - b * b).clamp_min(1e-12)
    s = torch.clamp((b * f - c * e) / denom, 0.0, 1.0)
    t = torch.clamp((b * s + f) / e.clamp_min(1e-12), 0.0, 1.0)
    s = torch.clamp((b * t - c) / a.clamp_min(1e-12), 0.0, 1.0)
    return p0 + s * d1, q0 + t * d2


def _sphere_sphere(ca, ra, cb, rb):
    """Two spheres (also capsule segment points): (point, normal b->a, distance)."""
    d = ca - cb
    dist = math.safe_norm(d)
    normal = d / dist
    midpoint = 0.5 * ((ca - normal * ra) + (cb + normal * rb))
    return midpoint, normal, (dist - ra - rb)[..., 0]


def _point_box(x, r, box_pos, box_quat, half):
    """Sphere of radius ``r`` at ``x`` against a box: (point, normal box->sphere, distance); exact inside and out."""
    local = math.quat_rotate_inv(box_quat, x - box_pos)
    clamped = torch.maximum(torch.minimum(local, half), -half)
    outside_vec = local - clamped
    out_dist = math.safe_norm(outside_vec)
    outside = (outside_vec.abs().amax(-1, keepdim=True) > 0)
    # inside: leave through the nearest face
    face_gap = half - local.abs()
    axis = torch.nn.functional.one_hot(face_gap.argmin(-1), 3).to(x.dtype)
    in_normal = axis * torch.where(local >= 0, 1.0, -1.0)
    normal_local = torch.where(outside, outside_vec / out_dist, in_normal)
    dist = torch.where(outside, out_dist, -(face_gap * axis).sum(-1, keepdim=True)) - r
    normal = math.quat_rotate(box_quat, normal_local)
    return x - normal * (r + 0.5 * dist), normal, dist[..., 0]


def _pair_contacts(kind, pa, qa, sa, pb, qb, sb):
    """Contacts of one shape pair for world geom poses; returns point (..., K, 3), normal (..., K, 3), distance (..., K)."""
    if kind.endswith("_plane"):
        normal = math.quat_rotate(qb, torch.zeros_like(pb) + pb.new_tensor([0.0, 0.0, 1.0]))
        if kind == "sphere_plane":
            pts, radius = pa.unsqueeze(-2), sa[..., :1].unsqueeze(-2)
        elif kind == "capsule_plane":
            pts, radius = torch.stack(_segment(pa, qa, sa), -2), sa[..., :1].unsqueeze(-2)
        else:  # box corners
            pts = pa.unsqueeze(-2) + math.quat_rotate(qa.unsqueeze(-2), _CORNERS.to(pa) * sa.unsqueeze(-2))
            radius = torch.zeros_like(pts[..., :1])
        normal = normal.unsqueeze(-2).expand_as(pts)
        dist = math.dot(pts - pb.unsqueeze(-2), normal) - radius
        return pts - normal * (radius + 0.5 * dist), normal, dist[..., 0]
    if kind == "box_box":
        corners_a = pa.unsqueeze(-2) + math.quat_rotate(qa.unsqueeze(-2), _CORNERS.to(pa) * sa.unsqueeze(-2))
        corners_b = pb.unsqueeze(-2) + math.quat_rotate(qb.unsqueeze(-2), _CORNERS.to(pb) * sb.unsqueeze(-2))
        zero = torch.zeros_like(corners_a[..., :1])
        pt_a, n_a, d_a = _point_box(corners_a, zero, pb.unsqueeze(-2), qb.unsqueeze(-2), sb.unsqueeze(-2))
        pt_b, n_b, d_b = _point_box(corners_b, zero, pa.unsqueeze(-2), qa.unsqueeze(-2), sa.unsqueeze(-2))
        return torch.cat((pt_a, pt_b), -2), torch.cat((n_a, -n_b), -2), torch.cat((d_a, d_b), -1)
    # sphere-like a (sphere, or points on a capsule's segment)
    if kind.startswith("sphere"):
        centres = pa.unsqueeze(-2)
    elif kind == "capsule_capsule":
        p0, p1 = _segment(pa, qa, sa)
        q0, q1 = _segment(pb, qb, sb)
        ca, cb = _segments_closest(p0, p1, q0, q1)
        pt, n, d = _sphere_sphere(ca, sa[..., :1], cb, sb[..., :1])
        return pt.unsqueeze(-2), n.unsqueeze(-2), d.unsqueeze(-1)
    else:  # capsule_box
        p0, p1 = _segment(pa, qa, sa)
        centres = torch.stack((p0, p1, _closest_on_segment(p0, p1, pb)), -2)
    ra = sa[..., :1].unsqueeze(-2).expand_as(centres[..., :1])
    if kind.endswith("_sphere"):
        pt, n, d = _sphere_sphere(centres, ra, pb.unsqueeze(-2), sb[..., :1].unsqueeze(-2))
    elif kind.endswith("_capsule"):
        q0, q1 = _segment(pb, qb, sb)
        nearest = _closest_on_segment(q0.unsqueeze(-2), q1.unsqueeze(-2), centres)
        pt, n, d = _sphere_sphere(centres, ra, nearest, sb[..., :1].unsqueeze(-2))
    else:
        pt, n, d = _point_box(centres, ra, pb.unsqueeze(-2), qb.unsqueeze(-2), sb.unsqueeze(-2))
    return pt, n, d


def contacts(sys: System, bodies: Bodies) -> Contacts:
    """Evaluate every candidate contact point of the model at the given ext body poses."""
    pos, normal, depth, body_a, body_b, friction = [], [], [], [], [], []
    for group in sys.contact_groups:
        k = POINTS_PER_PAIR[group.kind]
        geom = torch.cat((group.geom_a, group.geom_b))  # both sides' world poses at once
        body = sys.geom_body[geom]
        x, q = bodies.x_pos.index_select(1, body), bodies.x_quat.index_select(1, body)
        pos_a, pos_b = (x + math.quat_rotate(q, sys.geom_pos[geom])).chunk(2, 1)
        quat_a, quat_b = math.quat_mul(q, sys.geom_quat[geom]).chunk(2, 1)
        size_a, size_b = sys.geom_size[geom].expand(x.shape[0], -1, -1).chunk(2, 1)
        pt, n, dist = _pair_contacts(group.kind, pos_a, quat_a, size_a, pos_b, quat_b, size_b)
        pos.append(pt.flatten(1, 2))
        normal.append(n.flatten(1, 2))
        depth.append((group.margin[:, None] - dist).flatten(1, 2))
        body_a.append(sys.geom_body[group.geom_a].repeat_interleave(k))
        body_b.append(sys.geom_body[group.geom_b].repeat_interleave(k))
        friction.append(group.friction.repeat_interleave(k, dim=-1))
    if not pos:
        b = bodies.x_pos.shape[0]
        empty = bodies.x_pos.new_zeros(b, 0, 3)
        idx = sys.geom_body.new_zeros(0)
        return Contacts(empty, empty, bodies.x_pos.new_zeros(b, 0), idx, idx, bodies.x_pos.new_zeros(0))
    return Contacts(torch.cat(pos, 1), torch.cat(normal, 1), torch.cat(depth, 1), torch.cat(body_a),
                    torch.cat(body_b), torch.cat(friction, -1))
