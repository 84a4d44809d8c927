"""Contact geometry of the round shapes, ellipsoids and cylinders (``torchsim.collision`` dispatches here).

Geom sizes follow MuJoCo: an ellipsoid's ``size`` is its three semi-axes [m] along its frame's axes, a
cylinder's is ``(radius, half-height, -)`` [m] about its frame's z axis. Rotations are full frames ``(3, 3, ...)``
(a cylinder's x column is the fallback radial direction where its axis leaves none). Every function broadcasts
over the entity axes after the leading component axes, as ``torchsim.collision`` lays them out; iteration counts
are fixed, so the work is static and branch-free.

Pairs, with their error against MuJoCo's ``mj_geomDistance`` on random poses from 1 cm inside to 2 cm apart
(tests/test_round_geoms.py, float64; MuJoCo's own convex solver stops at ``ccd_tolerance`` = 1e-6 m):
- ellipsoid-plane: exact, the support point along the plane normal (one point);
- cylinder-plane: exact, 4 points on each cap's rim at quarter turns from the deepest one, so a cylinder rests
  stably on a cap or on its side (8 points);
- sphere-cylinder: exact, closed form;
- sphere-ellipsoid: Newton on the closest point's Lagrange multiplier, ``POINT_ITERATIONS`` steps; measured
  error below 1e-10 m;
- capsule-ellipsoid, capsule-cylinder: spheres at both ends of the capsule's segment and at its point nearest the
  other geom, found by ``SEGMENT_ITERATIONS`` bisections (3 points, like capsule-box). The distance is never too
  small and too large by at most the segment's length times ``2^-(SEGMENT_ITERATIONS + 1)`` (1/2048); measured
  up to 5e-7 m (a capsule against a 1 cm thin ellipsoid);
- ellipsoid-ellipsoid: maximises the separation ``-h_a(-n) - h_b(n)`` over the normal ``n`` (``h`` the support
  functions; the maximum is the signed distance, separated or penetrating) by ``ELLIPSOID_ITERATIONS`` Newton
  steps from the centre line, with the ellipsoids' curvature as the Hessian and the best of 3 step lengths. Any
  ``n`` gives a lower bound, so contacts err deep, never missed (one point). Measured from 1 cm inside to 2 cm
  apart: within 1e-6 m (MuJoCo's tolerance) for humanoid_CMU's hands, up to 9e-6 m for semi-axis ratios of 8;
  1-3 cm inside, as deep as the thin semi-axes themselves: up to 0.4 mm (hands) and 3.6 mm (ratio 8) too deep.
- cylinder-cylinder: a separating normal ``n*`` maximising the separation ``(pa - pb).n - width_a(n) -
  width_b(n)`` (the widths along ``n`` in closed form), climbed by ``NORMAL_ITERATIONS`` gradient steps from 7
  candidates (both axes, the normal between the axis segments' closest points, the normals at each cap rim's point
  nearest the other cylinder: the best of ``RIM_SAMPLES`` angles, then ``RIM_ITERATIONS`` bisections). 17 points:
  that separation itself, between the support points; each cap rim's 4 points at quarter turns from its nearest
  point, or from its support point along ``n*`` where either is inside the other cylinder, exact outside the other
  and measured below its support plane along ``n*`` inside, so a cylinder rests on a cap or its side (16 points).
  Any normal's separation is a lower bound on the signed distance and no point lies below it, so the distance is
  never too shallow: contacts err deep, never missed. Measured (5 seeds of 400 poses, 8 pairs of sizes,
  finger.xml's among them): 2 cm apart to 1 cm inside, up to 9.2e-5 m too deep (1.6e-5 m when apart); 1-3 cm
  inside, up to 5.7e-4 m too deep.

- ellipsoid-cylinder: one contact at the separating normal (:func:`separation_contact`, as ellipsoid-box: an
  ellipsoid is strictly convex, so one point), climbed from 6 candidates: the centre line, the cylinder's axis, its
  normal nearest the ellipsoid's centre, and the ellipsoid's normals at its points nearest the cylinder's axis
  segment (its side; ``segment_point``) and nearest each cap rim (``_nearest_rim``): each exact where that feature
  is the nearest one and the two are apart. Never too shallow. Measured against ``mj_geomDistance`` (3 seeds of 200
  poses, 6 ellipsoids from humanoid_CMU's hands and the dog's torso to semi-axis ratios of 8, 4 cylinders from a
  disc to a rod, the dog's target among them), 1 cm inside to 2 cm apart: within 1e-6 m (MuJoCo's tolerance) on
  98.8 % or more of each pair's poses, the worst 1.1e-4 m too deep (a 1 cm thin ellipsoid on a 1 cm thin disc),
  the dog's torso within 1e-6 m; 1-3 cm inside (as deep as the thin shapes are thick): up to 3.7e-3 m too deep
  (2.4e-5 m for the torso). The kernel strategy's step of this pair did not finish building in 30 minutes here.

Cylinder-box and ellipsoid-box pairs (``torchsim.collision._round_box``) climb the same separating normal
(:func:`separating_normal`, with a box's support function).
"""

import torch

from torchsim import spatial

POINT_ITERATIONS = 4
ELLIPSOID_ITERATIONS = 6
SEGMENT_ITERATIONS = 10
RIM_SAMPLES = 24
RIM_ITERATIONS = 10
NORMAL_ITERATIONS = 10
NORMAL_TURN = 0.3  # the largest turn of the separating normal per step [rad]
KINK = 1e-3  # rounding of the cylinders' support-point jumps in the separation's gradient
_STEP_SCALES = (1.0, 0.5, 0.25)
_TURNS = torch.tensor([1.0, 0.3, 0.1], dtype=torch.float64)  #: turns tried per step, in the step's angle
#: Rim points per cylinder cap on a plane, at quarter turns from the deepest one.
_RIM = torch.tensor([[1.0, 0.0, -1.0, 0.0], [0.0, 1.0, 0.0, -1.0]], dtype=torch.float64)
_QUARTERS = torch.tensor([0.0, 0.5, 1.0, 1.5], dtype=torch.float64).view(4, 1) * torch.pi


def _unit_or(d, fallback):
    """``d`` normalised, or the unit ``fallback`` where ``d`` vanishes (shorter than 1e-9: ``safe_norm``'s default
    floor, 1e-6, would shrink such a ``d`` instead, to a short non-unit vector)."""
    norm = spatial.safe_norm(d, 1e-30)
    return torch.where(norm > 1e-9, d / norm, fallback)


def _radial(axis, d, x_axis):
    """Unit direction of ``d`` perpendicular to the unit ``axis``; ``x_axis`` where ``d`` is along the axis."""
    return _unit_or(d - spatial.dot(d, axis) * axis, x_axis)


def plane_points(shape, pos, rot, size, normal):
    """Surface points ``(3, P, K, B)`` of an ellipsoid (K = 1, its deepest point) or cylinder (K = 8, its caps'
    rims) against a plane with unit ``normal (3, P, B)``; ``pos (3, P, B)``, ``rot (3, 3, P, B)``,
    ``size (3, P, 1)``."""
    if shape == "ellipsoid":
        return _support(pos, rot, size, -normal).unsqueeze(-2)
    axis, radius, half = rot[:, 2], size[0], size[1]
    u = _radial(axis, -normal, rot[:, 0])
    v = spatial.cross(axis, u)
    cos, sin = _RIM.to(u).view(2, 4, 1)
    rim = radius.unsqueeze(-2) * (u.unsqueeze(-2) * cos + v.unsqueeze(-2) * sin)
    caps = (pos + axis * half, pos - axis * half)
    return torch.cat([cap.unsqueeze(-2) + rim for cap in caps], -2)


def segment_point(shape, p0, p1, pos, rot, size):
    """The point of each segment ``p0-p1 (3, P, B)`` nearest an ellipsoid or cylinder (poses ``(3, P, B)``,
    ``(3, 3, P, B)``, sizes ``(3, P, 1)``), or deepest inside it: the signed distance is convex along the segment,
    so ``SEGMENT_ITERATIONS`` bisections on the sign of its slope (the surface normal along the segment) leave
    ``t`` within ``2^-(SEGMENT_ITERATIONS + 1)`` of the minimiser and the distance within that fraction of the
    segment's length."""
    d = p1 - p0
    lo = torch.zeros_like(p0[0])
    width = 1.0
    for _ in range(SEGMENT_ITERATIONS):
        width = 0.5 * width
        _, normal, _ = point_round(shape, p0 + (lo + width) * d, 0.0, pos, rot, size)
        lo = torch.where(spatial.dot(normal, d) > 0, lo, lo + width)
    return p0 + (lo + 0.5 * width) * d


def _support(pos, rot, size, d):
    """An ellipsoid's support point ``(3, ...)``, its point farthest along the (not necessarily unit) ``d``."""
    scaled = size * spatial.matvec(spatial.transpose(rot), d)
    return pos + spatial.matvec(rot, size * scaled / spatial.safe_norm(scaled))


def point_ellipsoid(x, r, pos, rot, size):
    """Sphere of radius ``r`` at ``x`` against an ellipsoid: (point, normal ellipsoid->sphere, distance).

    The closest surface point is ``y = s^2 x / (s^2 + l)`` (local frame, semi-axes ``s``) for the root ``l`` of
    ``|y / s| = 1``; Newton runs on ``(s^2 + l)``-linear ``1 / |y / s|``, exact for a sphere in one step, from
    ``l = 0`` and never below ``-min(s)^2`` (points inside)."""
    local = spatial.matvec(spatial.transpose(rot), x - pos)
    s2 = size * size
    floor = -0.999 * s2.amin(0)
    lam = torch.zeros_like(local[0])
    for _ in range(POINT_ITERATIONS):
        t = size * local / (s2 + lam)
        q = spatial.safe_norm(t)
        dq = -(t * t / (s2 + lam)).sum(0) / q
        lam = torch.maximum(lam + (q - q * q) / dq, floor)
    y = s2 * local / (s2 + lam)
    y = y / spatial.safe_norm(y / size)  # onto the surface, whatever the last step left
    n_local = spatial.normalize(y / s2)
    dist = spatial.dot(local - y, n_local) - r
    normal = spatial.matvec(rot, n_local)
    return x - normal * (r + 0.5 * dist), normal, dist


def point_cylinder(x, r, pos, rot, size):
    """Sphere of radius ``r`` at ``x`` against a cylinder, exact: (point, normal cylinder->sphere, distance)."""
    axis, radius, half = rot[:, 2], size[0], size[1]
    rel = x - pos
    z = spatial.dot(rel, axis)
    u = _radial(axis, rel, rot[:, 0])
    side, cap = spatial.dot(rel, u) - radius, z.abs() - half
    cap_dir = torch.where(z >= 0, 1.0, -1.0) * axis
    outside_vec = side.clamp_min(0) * u + cap.clamp_min(0) * cap_dir
    outside = (side > 0) | (cap > 0)
    out_dist = spatial.safe_norm(outside_vec)
    normal = torch.where(outside, outside_vec / out_dist, torch.where(side > cap, u, cap_dir))
    dist = torch.where(outside, out_dist, torch.maximum(side, cap)) - r
    return x - normal * (r + 0.5 * dist), normal, dist


def point_round(shape, x, r, pos, rot, size):
    """Spheres at ``x (3, ...)`` with radii ``r`` [m] against an ellipsoid or cylinder whose ``pos (3, ...)``,
    ``rot (3, 3, ...)`` and ``size (3, ...)`` broadcast with ``x``: (point, normal geom->sphere, distance [m])."""
    return (point_ellipsoid if shape == "ellipsoid" else point_cylinder)(x, r, pos, rot, size)


def ellipsoid_pair(pa, rot_a, sa, pb, rot_b, sb):
    """One contact of two ellipsoids (module docstring): point, normal b->a ``(3, P, 1, B)`` and distance
    ``(P, 1, B)``, for poses ``(3, P, B)``, ``(3, 3, P, B)`` and semi-axes ``(3, P, 1)``."""
    def separation(n):
        p_a, p_b = _support(pa, rot_a, sa, -n), _support(pb, rot_b, sb, n)
        return p_a, p_b, spatial.dot(p_a - p_b, n)

    n = _unit_or(pa - pb, rot_b[:, 2])
    p_a, p_b, f = separation(n)
    for _ in range(ELLIPSOID_ITERATIONS):
        normal_part = spatial.outer(n, n)
        # Newton on the tangential gap: d gap / d n = -(J_a + J_b), plus f for turning n itself; a negative f
        # (penetration) could make that indefinite, so it counts from zero
        hess = (_curvature(rot_a, sa, n) + _curvature(rot_b, sb, n) + normal_part
                + f.clamp_min(0) * (spatial.eye3(n, n.ndim - 1) - normal_part))
        step = spatial.spd_solve(hess, p_a - p_b - f * n)
        # the curvature changes fast on eccentric ellipsoids: keep the best of a few step lengths (ascent)
        best = (n, p_a, p_b, f)
        for scale in _STEP_SCALES:
            trial = spatial.normalize(n + scale * step)
            cand = (trial, *separation(trial))
            better = cand[3] > best[3]
            best = tuple(torch.where(better, c, b) for c, b in zip(cand, best))
        n, p_a, p_b, f = best
    return (0.5 * (p_a + p_b)).unsqueeze(-2), n.unsqueeze(-2), f.unsqueeze(-2)


def _curvature(rot, size, n):
    """``d s / d n (3, 3, ...)`` of an ellipsoid's support point ``s(n)`` (its radii of curvature there, even in
    ``n``; ``n`` lies in its kernel)."""
    scaled = size * spatial.matvec(spatial.transpose(rot), n)
    norm = spatial.safe_norm(scaled)
    u = scaled / norm
    rs = rot * size[None]  # R S
    rsu = spatial.matvec(rs, u)
    return (spatial.mm(rs, spatial.transpose(rs)) - spatial.outer(rsu, rsu)) / norm


def _first(mask, dim=-2):
    """The first true entry of ``mask`` along ``dim``, as a mask (selects without a gather); unrolled over the axis
    (a small one), as the row tracer of the kernel strategies has no ``cumsum``."""
    masks = mask.unbind(dim)
    firsts, seen = [masks[0]], masks[0]
    for m in masks[1:]:
        firsts.append(m & ~seen)
        seen = seen | m
    return torch.stack(firsts, dim)


def _width(rot, size, n):
    """Half the width of cylinders along unit ``n``: ``h |n.z| + r sqrt(1 - (n.z)^2)``."""
    nz = spatial.dot(n, rot[:, 2])
    return size[1] * nz.abs() + size[0] * (1 - nz * nz).clamp_min(0).sqrt()


def _offset(rot, size, n):
    """Support point of cylinders centred at the origin along unit ``n`` (their ``_width``'s gradient), its jumps
    where ``n`` is along or across the axis rounded by ``KINK``: mid-face there, and a direction to climb across."""
    axis = rot[:, 2]
    nz = spatial.dot(n, axis)
    radial = n - nz * axis
    return (size[1] * nz / (nz * nz + KINK * KINK).sqrt() * axis
            + size[0] * radial / (spatial.dot(radial, radial) + KINK * KINK).sqrt())


#: the frame columns across which each shape's support point jumps (ridges of the separation, where its maximum
#: often lies: a cylinder's side against a rim, a box's edge against anything)
_RIDGES = {"cylinder": (2,), "box": (0, 1, 2), "ellipsoid": ()}


def width(shape, rot, size, n):
    """Half the width of cylinders, boxes or ellipsoids (all centrally symmetric) along unit ``n``: their support
    function about their centre."""
    if shape == "cylinder":
        return _width(rot, size, n)
    local = spatial.matvec(spatial.transpose(rot), n)
    return (size * local.abs()).sum(0) if shape == "box" else spatial.safe_norm(size * local)


def offset(shape, rot, size, n):
    """The support point along unit ``n`` from the centre (``width``'s gradient): a cylinder's (``_offset``), a
    box's corner with its jumps rounded by ``KINK`` (mid-face along a face normal), an ellipsoid's (smooth)."""
    if shape == "cylinder":
        return _offset(rot, size, n)
    if shape == "ellipsoid":
        return _support(0.0, rot, size, n)
    local = spatial.matvec(spatial.transpose(rot), n)
    return spatial.matvec(rot, size * local / (local * local + KINK * KINK).sqrt())


def _ascend(n, a, b):
    """Normals ``n`` turned to raise the separation ``(pa - pb).n - width_a(n) - width_b(n)`` of shapes ``a, b =
    (shape, pos, rot, size)``, and it: each of ``NORMAL_ITERATIONS`` steps turns along its gradient ``pa - pb -
    offset_a(n) - offset_b(n)`` by the best of ``_TURNS`` of the step's angle, each also snapped across either
    shape's ridges (``_RIDGES``), or stays; the next angle is twice the one taken, or a tenth. The trials lie on a
    new axis at -3 (all of them at once)."""
    (shape_a, pa, rot_a, sa), (shape_b, pb, rot_b, sb) = a, b

    def sep(n, lead):
        return (spatial.dot(lead(pa - pb), n) - width(shape_a, lead(rot_a), lead(sa), n)
                - width(shape_b, lead(rot_b), lead(sb), n))

    trial_axis = lambda x: x.unsqueeze(-3)  # noqa: E731
    ridges = [trial_axis(rot[:, k]) for shape, rot in ((shape_a, rot_a), (shape_b, rot_b)) for k in _RIDGES[shape]]
    turns = _TURNS.to(n).repeat(1 + len(ridges)).view(-1, 1, 1)  # turned, then snapped across each ridge
    f = sep(n, lambda x: x)
    angle = torch.zeros_like(f) + NORMAL_TURN  # not full_like: the row tracer of the kernel strategies has none
    for _ in range(NORMAL_ITERATIONS):
        grad = pa - pb - offset(shape_a, rot_a, sa, n) - offset(shape_b, rot_b, sb, n)
        t = _unit_or(grad - spatial.dot(grad, n) * n, 0.0)  # none at a stationary n: the trials stay there
        turned = _unit_or(trial_axis(n) * torch.cos(angle.unsqueeze(-3) * turns[:3]) + trial_axis(t) * torch.sin(
            angle.unsqueeze(-3) * turns[:3]), trial_axis(n))
        snapped = [_unit_or(turned - spatial.dot(turned, ax) * ax, turned) for ax in ridges]
        trials = torch.cat([turned, *snapped], -3)
        f_trials = sep(trials, trial_axis)
        best = f_trials.amax(-3)
        pick = _first(f_trials == best.unsqueeze(-3), -3)
        better = best > f
        n = torch.where(better, torch.where(pick, trials, 0.0).sum(-3), n)
        angle = torch.where(better, 2 * angle * torch.where(pick, turns, 0.0).sum(-3), 0.1 * angle)
        angle = angle.clamp(max=NORMAL_TURN)
        f = torch.maximum(best, f)
    return n, f


def separating_normal(cands, a, b, climb_best_only=False):
    """The best separating normal ``(3, P, B)`` from ``b`` towards ``a`` and its separation ``(P, B)`` (a lower bound
    on the signed distance [m]: any normal's is), climbed from candidate directions ``cands (3, P, K, B)`` (any
    length, either sign; a vanishing one stands for b's z axis) by :func:`_ascend`; ``a, b = (shape, pos (3, P, B),
    rot (3, 3, P, B), size (3, P, 1))``. ``climb_best_only``: climb from the best candidate alone (a K-th of the
    work, where the candidates are the pair's separating axes and the best lies in the maximum's basin)."""
    pos_a, pos_b, rot_b = a[1], b[1], b[2]
    cands = _unit_or(cands, rot_b[:, 2].unsqueeze(-2))
    cands = torch.where(spatial.dot((pos_a - pos_b).unsqueeze(-2), cands) < 0, -cands, cands)
    a, b = (x[:1] + tuple(v.unsqueeze(-2) for v in x[1:]) for x in (a, b))
    if climb_best_only:
        sep = spatial.dot(a[1] - b[1], cands) - width(a[0], a[2], a[3], cands) - width(b[0], b[2], b[3], cands)
        cands = torch.where(_first(sep == sep.amax(-2, keepdim=True)), cands, 0.0).sum(-2, keepdim=True)
    cands, sep = _ascend(cands, a, b)
    return torch.where(_first(sep == sep.amax(-2, keepdim=True)), cands, 0.0).sum(-2), sep.amax(-2)


def separation_contact(cands, a, b, climb_best_only=False):
    """One contact at the best separating normal ``n*`` of shapes ``a, b`` (:func:`separating_normal`, same
    arguments): point ``(3, P, 1, B)`` midway across the gap from a's support point along ``-n*`` (mid-face where a
    face of a is flat along it: ``offset``), the normal ``n*`` (b towards a) ``(3, P, 1, B)`` and its separation
    ``(P, 1, B)``, never shallower than the signed distance."""
    n_star, sep = separating_normal(cands, a, b, climb_best_only)
    shape_a, pos_a, rot_a, size_a = a
    point = pos_a - offset(shape_a, rot_a, size_a, n_star) - 0.5 * sep * n_star
    return point.unsqueeze(-2), n_star.unsqueeze(-2), sep.unsqueeze(-2)


def ellipsoid_cylinder(pa, rot_a, sa, pb, rot_b, sb):
    """One contact of ellipsoids ``a`` and cylinders ``b`` (module docstring): point, normal b->a ``(3, P, 1, B)``
    and distance ``(P, 1, B)``, for poses ``(3, P, B)``, ``(3, 3, P, B)`` and sizes ``(3, P, 1)``."""
    ellipsoid = pa.unsqueeze(-2), rot_a.unsqueeze(-2), sa.unsqueeze(-2)
    # the ellipsoid's normals at its points nearest the cylinder's axis segment (its side), and each cap rim
    axis = rot_b[:, 2] * sb[1]
    side = segment_point("ellipsoid", pb - axis, pb + axis, pa, rot_a, sa)
    # (3, P, 2, B); select, not squeeze: the kernel strategies' row graphs have no squeeze
    rims = _rim(pb, rot_b, sb, _nearest_rim(pb, rot_b, sb, "ellipsoid", pa, rot_a, sa)).select(-2, 0)
    near = point_ellipsoid(torch.cat((side.unsqueeze(-2), rims), -2), 0.0, *ellipsoid)[1]
    cands = torch.cat((torch.stack((pa - pb, rot_b[:, 2], point_cylinder(pa, 0.0, pb, rot_b, sb)[1]), -2), -near), -2)
    return separation_contact(cands, ("ellipsoid", pa, rot_a, sa), ("cylinder", pb, rot_b, sb))


def _rim(pos, rot, size, angle):
    """Points ``(3, P, 2, A, B)`` on the cylinders' cap rims (top cap first) at ``angle (P, 2, A, B)`` [rad] from
    their x axes."""
    caps = torch.stack((pos + rot[:, 2] * size[1], pos - rot[:, 2] * size[1]), -2).unsqueeze(-2)
    x_axis, y_axis = rot[:, 0, :, None, None], rot[:, 1, :, None, None]
    return caps + size[0, ..., None, None] * (x_axis * torch.cos(angle) + y_axis * torch.sin(angle))


def _nearest_rim(pos, rot, size, other_shape, opos, orot, osize):
    """Angle ``(P, 2, 1, B)`` of each cap rim's point nearest the other geoms (ellipsoids or cylinders,
    ``other_shape``), or deepest in them: the best of
    ``RIM_SAMPLES`` angles, refined by ``RIM_ITERATIONS`` bisections on the sign of the distance's slope along the
    rim within a sample spacing either side."""
    other = tuple(o[..., None, None, :] for o in (opos, orot)) + (osize[..., None, None, :],)
    x_axis, y_axis = rot[:, 0, :, None, None], rot[:, 1, :, None, None]
    spacing = 2 * torch.pi / RIM_SAMPLES
    angles = torch.arange(RIM_SAMPLES, dtype=pos.dtype, device=pos.device).view(-1, 1) * spacing
    dist = point_round(other_shape, _rim(pos, rot, size, angles), 0.0, *other)[2]  # (P, 2, RIM_SAMPLES, B)
    lo = torch.where(_first(dist == dist.amin(-2, keepdim=True)), angles, 0.0).sum(-2, keepdim=True) - spacing
    width = 2 * spacing
    for _ in range(RIM_ITERATIONS):
        width = 0.5 * width
        mid = lo + width
        normal = point_round(other_shape, _rim(pos, rot, size, mid), 0.0, *other)[1]
        tangent = y_axis * torch.cos(mid) - x_axis * torch.sin(mid)
        lo = torch.where(spatial.dot(normal, tangent) > 0, lo, mid)
    return lo + 0.5 * width


def cylinder_pair(pa, rot_a, sa, pb, rot_b, sb):
    """Contacts of two cylinders (module docstring): points, normals b->a ``(3, P, 17, B)`` and distances
    ``(P, 17, B)``, for poses ``(3, P, B)``, ``(3, 3, P, B)`` and sizes ``(3, P, 1)``."""
    axis_a, axis_b = rot_a[:, 2], rot_b[:, 2]
    # closest points of the axis segments: side on side, the normal is along their difference
    p0, d1, q0, d2 = pa - axis_a * sa[1], 2 * axis_a * sa[1], pb - axis_b * sb[1], 2 * axis_b * sb[1]
    r = p0 - q0
    a, e, f, c, b = (spatial.dot(d1, d1), spatial.dot(d2, d2), spatial.dot(d2, r), spatial.dot(d1, r),
                     spatial.dot(d1, d2))
    s = torch.clamp((b * f - c * e) / (a * e - b * b).clamp_min(1e-12), 0.0, 1.0)
    t = torch.clamp((b * s + f) / e, 0.0, 1.0)
    s = torch.clamp((b * t - c) / a, 0.0, 1.0)
    ca, cb = p0 + s * d1, q0 + t * d2
    cross = _unit_or(spatial.cross(axis_a, axis_b), rot_b[:, 0])
    side_n = _unit_or(ca - cb, cross)
    # both ways at once, a's pairs then b's: the cap rims' points nearest the other cylinder, their normals
    pos, rot, size = (torch.cat(x, -2) for x in ((pa, pb), (rot_a, rot_b), (sa, sb)))
    other = tuple(torch.cat(x, -2) for x in ((pb, pa), (rot_b, rot_a), (sb, sa)))
    angle = _nearest_rim(pos, rot, size, "cylinder", *other)
    _, near, dist = point_cylinder(_rim(pos, rot, size, angle).squeeze(-2), 0.0, *(x.unsqueeze(-2) for x in other))
    near_a, near_b = near.chunk(2, -3)
    # the separating normal: the best of those candidates, climbed (any normal's separation is a lower bound;
    # it has a local maximum per face of the Minkowski difference)
    cands = torch.cat([axis_a.unsqueeze(-2), axis_b.unsqueeze(-2), side_n.unsqueeze(-2), near_a, -near_b], -2)
    n_star, sep = separating_normal(cands, ("cylinder", pa, rot_a, sa), ("cylinder", pb, rot_b, sb))
    n_out = torch.cat((n_star, -n_star), -2)  # out of the other cylinder
    # 4 points per cap rim at quarter turns from its nearest point; where that or the rim's support point along
    # n* is inside the other cylinder, from the support point
    support = torch.atan2(spatial.dot(-n_out, rot[:, 1]), spatial.dot(-n_out, rot[:, 0]))[:, None, None]
    support = support.expand_as(angle)
    inside = point_cylinder(_rim(pos, rot, size, support), 0.0, *(x[..., None, None, :] for x in other))[2]
    angle = torch.where((dist.unsqueeze(-2) <= 0) | (inside <= 0), support, angle)
    x = _rim(pos, rot, size, angle + _QUARTERS.to(angle)).flatten(-3, -2)  # (3, 2P, 8, B)
    # against the other: exact outside; inside, below its support plane along n*
    other = tuple(o.unsqueeze(-2) for o in other)
    _, normal, dist = point_cylinder(x, 0.0, *other)
    n_out = n_out.unsqueeze(-2)
    plane = spatial.dot(x - other[0], n_out) - _width(other[1], other[2], n_out)
    inside = dist <= 0
    dist, normal = torch.where(inside, plane, dist), torch.where(inside, n_out, normal)
    pt = x - 0.5 * normal * dist
    (pt_a, pt_b), (n_a, n_b), (d_a, d_b) = pt.chunk(2, -3), normal.chunk(2, -3), dist.chunk(2, -3)
    # the separation itself, between the support points (mid-face where a face is flat along n*)
    sep = sep.unsqueeze(-2)
    pt_s = (0.5 * (pa - _offset(rot_a, sa, n_star) + pb + _offset(rot_b, sb, n_star))).unsqueeze(-2)
    return (torch.cat((pt_a, pt_b, pt_s), -2), torch.cat((n_a, -n_b, n_star.unsqueeze(-2)), -2),
            torch.cat((d_a, d_b, sep), -2))
