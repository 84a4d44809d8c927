"""MuJoCo geoms -> torchsim geoms, and the contact pairs fixed at load time, grouped by shape pair."""

import warnings

import mujoco
import numpy as np
import torch

from torchsim import joint_space
from torchsim.collision import SHAPE_RANK
from torchsim.io_mjcf.bodies import FusedBodies, compose
from torchsim.io_mjcf.hfields import hfield_fields
from torchsim.io_mjcf.meshes import hull_fields
from torchsim.io_mjcf.subset import UnsupportedMJCFError, name
from torchsim.io_mjcf.tendons import solref_gains
from torchsim.system import MESH_POINTS_PER_PAIR, POINTS_PER_PAIR, ContactGroup, points_per_pair

SHAPE_NAME = {
    int(mujoco.mjtGeom.mjGEOM_PLANE): "plane",
    int(mujoco.mjtGeom.mjGEOM_SPHERE): "sphere",
    int(mujoco.mjtGeom.mjGEOM_CAPSULE): "capsule",
    int(mujoco.mjtGeom.mjGEOM_BOX): "box",
    int(mujoco.mjtGeom.mjGEOM_ELLIPSOID): "ellipsoid",
    int(mujoco.mjtGeom.mjGEOM_CYLINDER): "cylinder",
    int(mujoco.mjtGeom.mjGEOM_MESH): "mesh",
    int(mujoco.mjtGeom.mjGEOM_HFIELD): "hfield",
}


def geom_fields(m: mujoco.MjModel, fused: FusedBodies, contact_soft: bool) -> dict:
    """Geom frames relative to their fused body's COM, and the candidate contact pairs grouped by shape pair;
    ``contact_soft``: whether the contacts are soft (``load_mjcf(contact_model=...)``), which alone read the
    contact incidence tables."""
    gframe, gpos, gquat = [], [], []
    for g in range(m.ngeom):
        frame, *pose = fused.moving_frame(m, m.geom_bodyid[g])
        p, q = compose(*pose, m.geom_pos[g], m.geom_quat[g])
        gframe.append(frame)
        gpos.append(p)
        gquat.append(q)
    pairs = {}
    if not m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_CONTACT):
        pairs = candidate_pairs(m)
    geom_body = np.array([fused.body_of(m, m.geom_bodyid[g]) for g in range(m.ngeom)], dtype=np.int64)
    world = fused.index[0]
    # neither side moves (the world and mocap bodies, at rest): no impulse, and MuJoCo collides no such pair either
    pairs = {pair: row for pair, row in pairs.items() if (geom_body[list(pair)] != world).any()}
    groups = {}
    for (g1, g2), (friction, margin, *_) in pairs.items():
        names = [SHAPE_NAME.get(int(m.geom_type[g])) for g in (g1, g2)]
        if None in names:
            bad = g1 if names[0] is None else g2
            raise UnsupportedMJCFError(
                f"geom {name(m, mujoco.mjtObj.mjOBJ_GEOM, bad)!r} of type "
                f"{mujoco.mjtGeom(m.geom_type[bad]).name} can collide; contact geoms must be plane, sphere, "
                "capsule, box, ellipsoid, cylinder, mesh or hfield (set contype/conaffinity to 0 for visual-only "
                "geoms)")
        plane = g1 if names[0] == "plane" else g2
        if names.count("plane") == 1 and m.body_weldid[m.geom_bodyid[plane]] != 0:
            raise UnsupportedMJCFError(f"plane geom {name(m, mujoco.mjtObj.mjOBJ_GEOM, plane)!r} can collide and is "
                                       "not on the world body: planes must belong to the world body (not to a "
                                       "moving or mocap body)")
        (ga, na), (gb, nb) = sorted(((g1, names[0]), (g2, names[1])), key=lambda x: SHAPE_RANK[x[1]])
        if f"{na}_{nb}" not in POINTS_PER_PAIR | MESH_POINTS_PER_PAIR:
            geom_a, geom_b = (name(m, mujoco.mjtObj.mjOBJ_GEOM, g) for g in (ga, gb))
            raise UnsupportedMJCFError(
                f"geoms {geom_a!r} ({na}) and {geom_b!r} ({nb}) can collide, and {na}-{nb} contacts are not "
                "implemented; exclude the pair or set contype/conaffinity so that they cannot touch")
        groups.setdefault(f"{na}_{nb}", []).append((ga, gb, friction, margin, *pairs[(g1, g2)][2:]))
    for g in range(m.ngeom):
        if int(m.geom_type[g]) not in SHAPE_NAME and (m.geom_contype[g] or m.geom_conaffinity[g]):
            warnings.warn(f"geom {name(m, mujoco.mjtObj.mjOBJ_GEOM, g)!r}: non-primitive geom found no contact "
                          "partner and is used for mass only", stacklevel=3)
    contact_groups = tuple(
        ContactGroup(kind, *(torch.as_tensor(np.array([p[i] for p in rows]),
                                             dtype=torch.long if i < 2 else torch.float64) for i in range(4)))
        for kind, rows in sorted(groups.items()))
    # the soft contacts' parameters per contact point, in collision.contacts' order: groups, then pairs, then points
    # (each pair's row repeated over its points: a mesh pair has hundreds)
    hulls = hull_fields(m, [g for rows in groups.values() for p in rows for g in p[:2]])
    hull_vertices = hulls["geom_hull_vert"].shape[1]
    ordered = [p for kind, rows in sorted(groups.items()) for p in rows]
    repeats = np.array([points_per_pair(kind, hull_vertices) for kind, rows in sorted(groups.items()) for _ in rows],
                       dtype=np.int64)
    solref, solimp, invweight = (np.repeat(np.array([p[4 + i] for p in ordered]).reshape(-1, *shape), repeats, 0)
                                 for i, shape in enumerate(((2,), (5,), ())))
    pair_geoms = np.array([p[:2] for p in ordered], dtype=np.int64).reshape(-1, 2)
    bodies = np.repeat(geom_body[pair_geoms], repeats, 0)  # (C, 2) each point's two ext bodies
    return dict(
        geom_body=torch.as_tensor(geom_body, dtype=torch.long), geom_frame=torch.as_tensor(gframe, dtype=torch.long),
        contact_mocap=bool(np.any(np.array(gframe, dtype=np.int64)[pair_geoms] > world)),
        geom_pos=torch.as_tensor(np.array(gpos).reshape(-1, 3)), geom_quat=torch.as_tensor(np.array(gquat).reshape(-1, 4)),
        geom_size=torch.as_tensor(m.geom_size.copy()), **hulls, **hfield_fields(m, groups),
        contact_groups=contact_groups,
        contact_gains=torch.as_tensor(solref_gains(m, solref, solimp)), contact_solimp=torch.as_tensor(solimp),
        contact_invweight=torch.as_tensor(invweight), contact_solimp_square=bool((solimp[:, 4] == 2).all()),
        contact_pyramidal=m.opt.cone == int(mujoco.mjtCone.mjCONE_PYRAMIDAL),
        **contact_incidence(bodies if contact_soft else bodies[:0], fused.index[0]),
    )


#: The most ordered pairs of contact points on a common body the soft contacts' tables may hold (``contact_incidence``):
#: each pair is a row of the ``(Q, 2)`` table (16 bytes) and a product per env per substep; a body's ``K`` points make
#: ``K^2`` of them. robosuite's GR1 (7568 points, its boxes touching each other) makes 9.4 million; dm_control's
#: fruit fly (drosophila_fused, 439374 points on 85 capped mesh hulls) 14.8 billion, 110 GiB of table alone.
MAX_SOFT_CONTACT_PAIRS = 50_000_000

#: Contact points above which ``contact_model='soft'`` warns of its cost: the normals are solved as one dense ``C x C``
#: system per env and substep (``soft_contacts.normal_impulses``), ``8 C^2`` bytes and ``~C^3 / 3`` multiply-adds in
#: float64, and the compiled step unrolls its factorisation over ``C``. dm_control's dog_v2 (thousands of points on
#: its capped hulls) spent over 10 minutes in one eager step.
SOFT_CONTACT_POINTS_WARN = 1024


def contact_incidence(bodies: np.ndarray, world: int) -> dict:
    """Load-time tables of which contact points act on which moving body, for the soft contacts' coupled solve
    (``torchsim.soft_contacts``): one row per (point, body), point ``(P,)``, ext body ``(P,)`` and sign ``(P,)``
    (+1 for the pair's first body, which the normal pushes, -1 for the second), grouped by body (then by point);
    and ``(Q, 2)`` the ordered pairs of rows on a common body. ``bodies (C, 2)``: each point's two ext bodies
    (none for impulse contacts, which do not read the tables); ``world``: the world's. A body's ``K`` points make
    ``K^2`` pairs: more than ``MAX_SOFT_CONTACT_PAIRS`` in all is refused, naming the count, before any is built."""
    bodies = np.asarray(bodies, dtype=np.int64).reshape(-1, 2)
    body = bodies.reshape(-1)
    point = np.repeat(np.arange(len(bodies), dtype=np.int64), 2)
    sign = np.tile(np.array([1.0, -1.0]), len(bodies))
    keep = body != world
    body, point, sign = body[keep], point[keep], sign[keep]
    order = np.lexsort((sign, point, body))  # as sorted (body, point, sign) rows
    body, point, sign = body[order], point[order], sign[order]
    per_body = np.bincount(body) if len(body) else np.zeros(0, np.int64)
    num_pairs = int((per_body.astype(np.int64) ** 2).sum())
    if num_pairs > MAX_SOFT_CONTACT_PAIRS:
        raise UnsupportedMJCFError(
            f"contact_model='soft' couples every pair of contact points on a common body: this model's "
            f"{len(bodies)} contact points make {num_pairs:,} such pairs (the busiest body has {per_body.max()} "
            f"points), more than the {MAX_SOFT_CONTACT_PAIRS:,} torchsim builds (torchsim.io_mjcf.geoms."
            "MAX_SOFT_CONTACT_PAIRS); load it with contact_model='impulse', or exclude geom pairs "
            "(<contact><exclude>, contype/conaffinity) or cap mesh hulls lower (max_hull_vertices) to have fewer "
            "points")
    if len(bodies) > SOFT_CONTACT_POINTS_WARN:
        warnings.warn(
            f"contact_model='soft' solves this model's {len(bodies)} contact points as one dense "
            f"{len(bodies)} x {len(bodies)} system per env and substep ({8 * len(bodies) ** 2 / 2 ** 20:,.0f} MiB per "
            f"env in float64, ~{len(bodies) ** 3 / 3e9:,.1f} G multiply-adds): its steps will be slow and its "
            "compiled step may not build (torchsim.io_mjcf.geoms.SOFT_CONTACT_POINTS_WARN); contact_model='impulse', "
            "excluded geom pairs or lower max_hull_vertices make fewer")
    body, point, sign, pairs = joint_space.incidence_columns(body, point, sign)
    return dict(contact_inc_point=point, contact_inc_body=body, contact_inc_sign=sign, contact_inc_pairs=pairs)


def candidate_pairs(m: mujoco.MjModel) -> dict:
    """Geom pairs that MuJoCo's broadphase filters would let collide: {(g1, g2): (friction, margin, solref (2,),
    solimp (5,), invweight)}, with MuJoCo's rules for combining the two geoms' values (:func:`_mixed`)."""
    weld, parent = m.body_weldid, m.body_parentid
    filter_parent = not m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_FILTERPARENT)
    excluded = np.array(sorted({int(s) for s in m.exclude_signature}), dtype=np.int64)
    body, contype, conaffinity = m.geom_bodyid.astype(np.int64), m.geom_contype, m.geom_conaffinity
    pairs, condims = {}, {}
    for g1 in range(m.ngeom):  # the filters on all of g1's partners at once: one pass per geom, not per pair
        g2 = np.arange(g1 + 1, m.ngeom)
        b1, b2 = body[g1], body[g2]
        w1, w2 = weld[b1], weld[b2]
        keep = (w1 != w2) & ((contype[g1] & conaffinity[g2]) | (contype[g2] & conaffinity[g1]) != 0)
        if filter_parent and w1:
            keep &= ~((w2 != 0) & ((weld[parent[w1]] == w2) | (weld[parent[w2]] == w1)))
        keep &= ~np.isin((np.minimum(b1, b2) << 16) + np.maximum(b1, b2), excluded)
        for g2 in g2[keep].tolist():
            condim = max(m.geom_condim[g1], m.geom_condim[g2])
            friction = max(m.geom_friction[g1, 0], m.geom_friction[g2, 0])
            margin = max(m.geom_margin[g1], m.geom_margin[g2])
            pairs[(g1, g2)] = (_sliding_friction(condim, friction), margin, *_mixed(m, g1, g2),
                               _invweight(m, g1, g2))
            condims[(g1, g2)] = condim
    for p in range(m.npair):
        g1, g2 = sorted((m.pair_geom1[p], m.pair_geom2[p]))
        pairs[(g1, g2)] = (_sliding_friction(m.pair_dim[p], m.pair_friction[p, 0]), m.pair_margin[p],
                           m.pair_solref[p].copy(), m.pair_solimp[p].copy(), _invweight(m, g1, g2))
        condims[(g1, g2)] = m.pair_dim[p]
    _warn_condim(m, {pair: condim for pair, condim in condims.items() if condim > 3})
    return pairs


def _warn_condim(m: mujoco.MjModel, beyond_sliding: dict) -> None:
    """One warning for every pair whose ``condim`` (4, 6) asks for torsional or rolling friction, which torchsim does
    not model: the count and the first few pairs (a model may have hundreds, e.g. a hand's fingertips on a floor)."""
    if not beyond_sliding:
        return
    geom = lambda g: repr(name(m, mujoco.mjtObj.mjOBJ_GEOM, g))  # noqa: E731
    shown = [f"{geom(g1)} and {geom(g2)} (condim {c})" for (g1, g2), c in list(beyond_sliding.items())[:3]]
    more = f" and {len(beyond_sliding) - 3} more" if len(beyond_sliding) > 3 else ""
    warnings.warn(f"{len(beyond_sliding)} geom pairs have condim 4 or 6, {', '.join(shown)}{more}: torchsim models "
                  "their sliding friction only (no torsional or rolling friction)", stacklevel=4)


def _mixed(m: mujoco.MjModel, g1: int, g2: int):
    """A geom pair's ``solref`` and ``solimp`` as MuJoCo combines them: weighted by ``solmix`` (an even split where
    both are ~0), except that a direct ``solref`` (non-positive) on either side takes the smaller of each."""
    mix1, mix2 = m.geom_solmix[g1], m.geom_solmix[g2]
    tiny = mujoco.mjMINVAL
    mix = 0.5 if mix1 < tiny and mix2 < tiny else 0.0 if mix1 < tiny else 1.0 if mix2 < tiny else mix1 / (mix1 + mix2)
    ref1, ref2 = m.geom_solref[g1], m.geom_solref[g2]
    solref = mix * ref1 + (1 - mix) * ref2 if ref1[0] > 0 and ref2[0] > 0 else np.minimum(ref1, ref2)
    return solref, mix * m.geom_solimp[g1] + (1 - mix) * m.geom_solimp[g2]


def _invweight(m: mujoco.MjModel, g1: int, g2: int) -> float:
    """MuJoCo's approximate inverse mass of a contact between two geoms at ``qpos0``: their bodies' translational
    ``body_invweight0`` (the world's is 0), the ``A0`` its soft contact's regulariser scales with."""
    return float(m.body_invweight0[m.geom_bodyid[g1], 0] + m.body_invweight0[m.geom_bodyid[g2], 0])


def _sliding_friction(condim: int, friction: float) -> float:
    """A pair's sliding friction by MuJoCo's ``condim``: 1 is frictionless, 3 sliding friction; 4 and 6 add
    torsional and rolling friction, which torchsim does not model (:func:`_warn_condim`)."""
    return 0.0 if condim == 1 else friction
