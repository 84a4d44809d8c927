"""Loading costs time linear-ish in the model: the loader's tables are built with numpy passes, not Python loops
over pairs, and each equals the brute-force loop it replaced (checked here on small inputs; speed is never
asserted). The soft contacts' pair table, quadratic in a body's contact points by its meaning, is refused beyond
``geoms.MAX_SOFT_CONTACT_PAIRS`` by count, before it is built (dm_control's fruit fly would make 14.8 billion)."""

import warnings

import mujoco
import numpy as np
import pytest

import torchsim
from torchsim.io_mjcf import geoms
from torchsim.io_mjcf.geoms import _invweight, _mixed, _sliding_friction
from torchsim.io_mjcf.meshes import _planes
from models import F64
from test_load_tables import BODIES_THAT_TOUCH

# A chain (parent-child pairs filtered), a welded body (same weld), an excluded pair, a geom that collides with
# nothing (contype 0) and one only the plane's conaffinity admits, and an explicit <pair>.
FILTERS = """
<mujoco><worldbody>
  <geom name="floor" type="plane" size="5 5 .1" conaffinity="3"/>
  <body name="a" pos="0 0 1"><freejoint/><geom type="sphere" size=".1"/>
    <body name="b" pos=".3 0 0"><joint type="hinge"/><geom type="capsule" size=".05 .1"/>
      <body name="c" pos=".3 0 0"><joint type="hinge"/><geom type="box" size=".1 .1 .1"/>
        <body name="c_welded" pos=".1 0 0"><geom type="sphere" size=".05"/></body></body></body></body>
  <body name="d" pos="1 0 1"><freejoint/><geom name="d1" type="sphere" size=".1"/>
    <geom type="box" size=".1 .1 .1" contype="0" conaffinity="0"/></body>
  <body name="e" pos="2 0 1"><freejoint/><geom name="e1" type="sphere" size=".1" contype="2" conaffinity="0"/></body>
  <body name="f" pos="3 0 1"><freejoint/><geom name="f1" type="capsule" size=".05 .1"/></body>
</worldbody>
<contact><exclude body1="a" body2="d"/><pair geom1="e1" geom2="d1"/></contact></mujoco>"""


def brute_force_pairs(m: mujoco.MjModel) -> dict:
    """``geoms.candidate_pairs`` as the loop over every pair of geoms it replaced."""
    weld, parent = m.body_weldid, m.body_parentid
    filter_parent = not m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_FILTERPARENT)
    excluded = {int(s) for s in m.exclude_signature}
    pairs = {}
    for g1 in range(m.ngeom):
        for g2 in range(g1 + 1, m.ngeom):
            b1, b2 = m.geom_bodyid[g1], m.geom_bodyid[g2]
            w1, w2 = weld[b1], weld[b2]
            if w1 == w2 or not (m.geom_contype[g1] & m.geom_conaffinity[g2]
                                or m.geom_contype[g2] & m.geom_conaffinity[g1]):
                continue
            if filter_parent and w1 and w2 and (weld[parent[w1]] == w2 or weld[parent[w2]] == w1):
                continue
            if ((min(b1, b2) << 16) + max(b1, b2)) in excluded:
                continue
            condim = max(m.geom_condim[g1], m.geom_condim[g2])
            friction = max(m.geom_friction[g1, 0], m.geom_friction[g2, 0])
            margin = max(m.geom_margin[g1], m.geom_margin[g2])
            pairs[(g1, g2)] = (_sliding_friction(condim, friction), margin, *_mixed(m, g1, g2),
                               _invweight(m, g1, g2))
    for p in range(m.npair):
        g1, g2 = sorted((m.pair_geom1[p], m.pair_geom2[p]))
        pairs[(g1, g2)] = (_sliding_friction(m.pair_dim[p], m.pair_friction[p, 0]), m.pair_margin[p],
                           m.pair_solref[p].copy(), m.pair_solimp[p].copy(), _invweight(m, g1, g2))
    return pairs


def test_candidate_pairs_equal_the_pairwise_loop():
    """The broadphase filters, one numpy pass per geom: the same pairs, in the same order, with the same values;
    the model exercises every filter, with the parent filter on and off (then a parent and child may touch)."""
    counts = []
    for xml in (FILTERS, FILTERS.replace("<mujoco>", '<mujoco><option><flag filterparent="disable"/></option>')):
        m = mujoco.MjModel.from_xml_string(xml)
        expected, pairs = brute_force_pairs(m), geoms.candidate_pairs(m)
        assert list(pairs) == list(expected) and 0 < len(pairs) < m.ngeom * (m.ngeom - 1) // 2
        for key, values in expected.items():
            assert all(np.array_equal(x, y) for x, y in zip(pairs[key], values)), key
        counts.append(len(pairs))
    assert counts[0] < counts[1]


def greedy_planes(planes: np.ndarray, tolerance: np.ndarray):
    """The plane merging loop ``meshes._planes`` replaced: each triangle's plane joins the first merged plane it
    matches within ``tolerance``, else starts one."""
    merged, plane_of = [], []
    for p in planes:
        same = [k for k, q in enumerate(merged) if (np.abs(p - q) <= tolerance).all()]
        plane_of.append(same[0] if same else len(merged))
        if not same:
            merged.append(p)
    return np.array(merged), plane_of


def test_hull_planes_merge_as_the_greedy_loop():
    """A box's hull (12 triangles, 6 planes) and random hulls' triangles of near-duplicate planes: the merged
    planes and each triangle's plane equal the greedy loop's."""
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
    faces = [(0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1), (2, 3, 7), (2, 7, 6), (0, 2, 6),
             (0, 6, 4), (1, 5, 7), (1, 7, 3)]
    planes, plane_of = _planes(corners, np.array(faces), np.zeros(3))
    assert planes.shape == (6, 4) and sorted(set(plane_of)) == list(range(6))
    rng = np.random.default_rng(0)
    for _ in range(20):
        verts = rng.normal(size=(40, 3))
        tri = rng.integers(0, 40, (int(rng.integers(1, 120)), 3))
        tri = tri[(tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 0] != tri[:, 2])]
        tri = np.concatenate([tri, tri[rng.integers(0, len(tri), len(tri))][:, [1, 2, 0]]])  # the same planes again
        planes, plane_of = _planes(verts, tri, verts.mean(0))
        a, b, c = (verts[tri[:, i]] for i in range(3))
        normal = np.cross(b - a, c - a)
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        offset = (normal * a).sum(1)
        flip = np.where(normal @ verts.mean(0) > offset, -1.0, 1.0)[:, None]
        raw = np.concatenate([normal, offset[:, None]], 1) * flip
        expected, expected_of = greedy_planes(raw, np.array([1e-5, 1e-5, 1e-5, 1e-5 * np.abs(verts).max()]))
        assert plane_of == expected_of and np.array_equal(planes, expected) and len(planes) < len(tri)


def test_soft_pair_tables_are_refused_by_count(monkeypatch):
    """Beyond the bound the soft contacts' pair table is refused by count (the sum over moving bodies of their
    points squared) and the remedy named; impulse contacts, which build no table, load the same model."""
    soft = torchsim.load_mjcf(BODIES_THAT_TOUCH, dtype=F64, contact_model="soft")
    count = soft.contact_inc_pairs.shape[0]
    per_body = np.bincount(soft.contact_inc_body.numpy())
    assert count == int((per_body ** 2).sum())
    monkeypatch.setattr(geoms, "MAX_SOFT_CONTACT_PAIRS", count - 1)
    with pytest.raises(torchsim.UnsupportedMJCFError, match=f"make {count:,} such pairs.*contact_model='impulse'"):
        torchsim.load_mjcf(BODIES_THAT_TOUCH, dtype=F64, contact_model="soft")
    impulse = torchsim.load_mjcf(BODIES_THAT_TOUCH, dtype=F64)
    assert impulse.num_contacts == soft.num_contacts and impulse.contact_inc_pairs.shape == (0, 2)
    monkeypatch.setattr(geoms, "MAX_SOFT_CONTACT_PAIRS", count)
    assert torchsim.load_mjcf(BODIES_THAT_TOUCH, dtype=F64, contact_model="soft").contact_inc_pairs.shape[0] == count


def test_soft_contacts_warn_of_a_large_dense_solve(monkeypatch):
    """The soft normals are one dense ``C x C`` solve per env and substep: beyond ``SOFT_CONTACT_POINTS_WARN``
    points the loader says so, with the count and the per-env memory; at the bound it stays quiet."""
    points = torchsim.load_mjcf(BODIES_THAT_TOUCH, dtype=F64).num_contacts
    monkeypatch.setattr(geoms, "SOFT_CONTACT_POINTS_WARN", points - 1)
    with pytest.warns(UserWarning, match=f"{points} contact points as one dense {points} x {points} system"):
        torchsim.load_mjcf(BODIES_THAT_TOUCH, dtype=F64, contact_model="soft")
    monkeypatch.setattr(geoms, "SOFT_CONTACT_POINTS_WARN", points)
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        torchsim.load_mjcf(BODIES_THAT_TOUCH, dtype=F64, contact_model="soft")
