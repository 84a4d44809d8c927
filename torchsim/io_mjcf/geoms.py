"""MuJoCo geoms -> torchsim geoms, and the contact pairs fixed at load time, grouped by shape pair."""

import warnings

import mujoco
import numpy as np
import torch

from torchsim.collision import SHAPE_RANK
from torchsim.io_mjcf.bodies import FusedBodies, compose
from torchsim.io_mjcf.subset import UnsupportedMJCFError, name
from torchsim.system import POINTS_PER_PAIR, ContactGroup

SHAPE_NAME = {
    int(mujoco.mjtGeom.mjGEOM_PLANE): "plane",
    int(mujoco.mjtGeom.mjGEOM_SPHERE): "sphere",
    int(mujoco.mjtGeom.mjGEOM_CAPSULE): "capsule",
    int(mujoco.mjtGeom.mjGEOM_BOX): "box",
    int(mujoco.mjtGeom.mjGEOM_ELLIPSOID): "ellipsoid",
    int(mujoco.mjtGeom.mjGEOM_CYLINDER): "cylinder",
}


def geom_fields(m: mujoco.MjModel, fused: FusedBodies) -> dict:
    """Geom frames relative to their fused body's COM, and the candidate contact pairs grouped by shape pair."""
    gpos, gquat = [], []
    for g in range(m.ngeom):
        b = m.geom_bodyid[g]
        p, q = compose(*fused.frame[b], m.geom_pos[g], m.geom_quat[g])
        gpos.append(p - fused.com_of(m, b))
        gquat.append(q)
    pairs = {}
    if not m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_CONTACT):
        pairs = candidate_pairs(m)
    groups = {}
    for (g1, g2), (friction, margin) in pairs.items():
        names = [SHAPE_NAME.get(int(m.geom_type[g])) for g in (g1, g2)]
        if None in names:
            bad = g1 if names[0] is None else g2
            raise UnsupportedMJCFError(
                f"geom {name(m, mujoco.mjtObj.mjOBJ_GEOM, bad)!r} of type "
                f"{mujoco.mjtGeom(m.geom_type[bad]).name} can collide; contact geoms must be plane, sphere, "
                "capsule, box, ellipsoid or cylinder (set contype/conaffinity to 0 for visual-only geoms)")
        if names.count("plane") == 1 and m.body_weldid[m.geom_bodyid[g1 if names[0] == "plane" else g2]] != 0:
            raise UnsupportedMJCFError("planes must belong to the world body")
        (ga, na), (gb, nb) = sorted(((g1, names[0]), (g2, names[1])), key=lambda x: SHAPE_RANK[x[1]])
        if f"{na}_{nb}" not in POINTS_PER_PAIR:
            geom_a, geom_b = (name(m, mujoco.mjtObj.mjOBJ_GEOM, g) for g in (ga, gb))
            raise UnsupportedMJCFError(
                f"geoms {geom_a!r} ({na}) and {geom_b!r} ({nb}) can collide, and {na}-{nb} contacts are not "
                "implemented; exclude the pair or set contype/conaffinity so that they cannot touch")
        groups.setdefault(f"{na}_{nb}", []).append((ga, gb, friction, margin))
    for g in range(m.ngeom):
        if int(m.geom_type[g]) not in SHAPE_NAME and (m.geom_contype[g] or m.geom_conaffinity[g]):
            warnings.warn(f"geom {name(m, mujoco.mjtObj.mjOBJ_GEOM, g)!r}: non-primitive geom found no contact "
                          "partner and is used for mass only", stacklevel=3)
    contact_groups = tuple(
        ContactGroup(kind, *(torch.as_tensor([p[i] for p in rows], dtype=torch.long if i < 2 else torch.float64)
                             for i in range(4)))
        for kind, rows in sorted(groups.items()))
    return dict(
        geom_body=torch.as_tensor([fused.body_of(m, m.geom_bodyid[g]) for g in range(m.ngeom)], dtype=torch.long),
        geom_pos=torch.as_tensor(np.array(gpos).reshape(-1, 3)), geom_quat=torch.as_tensor(np.array(gquat).reshape(-1, 4)),
        geom_size=torch.as_tensor(m.geom_size.copy()), contact_groups=contact_groups,
    )


def candidate_pairs(m: mujoco.MjModel) -> dict:
    """Geom pairs that MuJoCo's broadphase filters would let collide: {(g1, g2): (friction, margin)}."""
    weld, parent = m.body_weldid, m.body_parentid
    filter_parent = not m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_FILTERPARENT)
    excluded = {int(s) for s in m.exclude_signature}
    pairs = {}
    for g1 in range(m.ngeom):
        for g2 in range(g1 + 1, m.ngeom):
            b1, b2 = m.geom_bodyid[g1], m.geom_bodyid[g2]
            w1, w2 = weld[b1], weld[b2]
            if w1 == w2:
                continue
            if not (m.geom_contype[g1] & m.geom_conaffinity[g2] or m.geom_contype[g2] & m.geom_conaffinity[g1]):
                continue
            if filter_parent and w1 and w2 and (weld[parent[w1]] == w2 or weld[parent[w2]] == w1):
                continue
            if ((min(b1, b2) << 16) + max(b1, b2)) in excluded:
                continue
            pairs[(g1, g2)] = (max(m.geom_friction[g1, 0], m.geom_friction[g2, 0]), max(m.geom_margin[g1], m.geom_margin[g2]))
    for p in range(m.npair):
        g1, g2 = sorted((m.pair_geom1[p], m.pair_geom2[p]))
        pairs[(g1, g2)] = (m.pair_friction[p, 0], m.pair_margin[p])
    return pairs
