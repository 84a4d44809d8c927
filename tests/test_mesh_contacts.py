"""Mesh contacts (the convex hull MuJoCo compiles, ``torchsim.collision_mesh``) against MuJoCo's ``mj_collision``.

Both sides read the same float32 mesh vertices, so where a contact is a hull vertex against a face (a mesh on a
plane, a corner on a face) points, normals and distances agree to float64 round-off: checked to 1e-9 m. MuJoCo's
own contacts are its convex solver's: one deepest point per pair, or with its multi-contact polygon clipping (MuJoCo
4) up to 4 points of the touching faces; ours are every hull vertex against the other geom, and for boxes, hulls
and cylinders the other's points and one separating-axis contact. So a face-to-face contact is checked both ways
where both report vertices (ours among MuJoCo's, MuJoCo's deepest among ours), and sampled poses by the smallest
distance of each against ``mj_geomDistance`` (MuJoCo's own tolerance: 1e-6 m).
"""

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from models import F64, METHODS, rest_pose
from torchsim import lanes
from torchsim.collision import contacts
from torchsim.io_mjcf import UnsupportedMJCFError, mujoco_model
from torchsim.io_mjcf.meshes import MAX_HULL_VERTICES
from torchsim.kinematics import with_world
from torchsim.system import points_per_pair

TET = "0 0 0  0.2 0 0  0 0.2 0  0 0 0.2"
CUBE = " ".join(f"{x} {y} {z}" for x in (-0.1, 0.1) for y in (-0.1, 0.1) for z in (-0.1, 0.1))
# 7 points in general position, all on the hull, and an interior point the hull leaves out
IRREGULAR = ("0 0 0.12  0.1 0.02 -0.03  -0.05 0.09 -0.04  -0.06 -0.08 -0.02  0.02 -0.01 -0.09  0.07 0.07 0.05  "
             "-0.08 0.01 0.06  0.01 0.01 0.01")
# 100 random points on a 10 cm sphere, all on its hull: more hull vertices than torchsim collides
_BALL_POINTS = np.random.default_rng(0).normal(size=(100, 3))
BALL = " ".join(map(str, (0.1 * _BALL_POINTS / np.linalg.norm(_BALL_POINTS, axis=1, keepdims=True)).ravel()))
SCENE = """
<mujoco>
  <option gravity="0 0 0"/>
  <asset><mesh name="tet" vertex="{tet}"/><mesh name="cube" vertex="{cube}"/><mesh name="irregular" vertex="{irr}"/>
    <mesh name="ball" vertex="{ball}"/></asset>
  <worldbody>
    {floor}
    <body name="a" pos="{pos_a}" euler="{euler_a}"><freejoint/><geom name="a" {geom_a}/></body>
    {body_b}
  </worldbody>
</mujoco>
"""
FLOOR = '<geom name="floor" type="plane" size="2 2 0.1"/>'
GEOMS = {"tet": 'type="mesh" mesh="tet"', "cube": 'type="mesh" mesh="cube"', "irregular": 'type="mesh" mesh="irregular"',
         "ball": 'type="mesh" mesh="ball"',
         "sphere": 'type="sphere" size="0.05"', "capsule": 'type="capsule" size="0.03 0.08"',
         "box": 'type="box" size="0.1 0.1 0.1"', "cylinder": 'type="cylinder" size="0.05 0.04"',
         "ellipsoid": 'type="ellipsoid" size="0.05 0.04 0.03"'}
ROUNDOFF = 1e-9  # [m] float64 round-off on the same float32 vertices


def _scene(geom_a, pos_a="0 0 0", euler_a="0 0 0", geom_b=None, pos_b="0 0 0", euler_b="0 0 0"):
    """``geom_a`` on a free body; on the floor without ``geom_b``, otherwise against ``geom_b`` on a second."""
    body_b = (f'<body name="b" pos="{pos_b}" euler="{euler_b}"><freejoint/><geom name="b" {GEOMS[geom_b]}/></body>'
              if geom_b else "")
    return SCENE.format(tet=TET, cube=CUBE, irr=IRREGULAR, ball=BALL, floor="" if geom_b else FLOOR, pos_a=pos_a,
                        euler_a=euler_a, geom_a=GEOMS[geom_a], body_b=body_b)


def _ours(xml, qpos, **options):
    """torchsim's contacts at MuJoCo ``qpos (B, nq)``: the System and (pos (3, C, B), normal, distance (C, B));
    ``options``: ``load_mjcf``'s."""
    sys = torchsim.load_mjcf(xml, dtype=F64, **options)
    state = torchsim.init(sys, torch.as_tensor(qpos), torch.zeros(len(qpos), sys.nv, dtype=F64))
    con = contacts(sys, with_world(*(lanes.to_lanes(x, 1) for x in state[:4])))
    return sys, con.pos.numpy(), con.normal.numpy(), -con.depth.numpy()


def _compare(xml, **options):
    """MuJoCo's contacts and ours (those touching: distance <= 0) at the model's pose, as (pos (n, 3), normal from
    torchsim's geom b towards a (n, 3), distance (n,)), each sorted by distance; ``options``: ``load_mjcf``'s (MuJoCo's
    side is the model it builds the System from)."""
    m = mujoco_model(xml, options.get("max_hull_vertices"))
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    sys, pos, normal, dist = _ours(xml, d.qpos[None], **options)
    (group,) = sys.contact_groups
    geom_b = int(group.geom_b[0])
    # MuJoCo's frame normal points from its geom1 to its geom2
    mj = [(c.pos, c.frame[:3] * (1 if c.geom[0] == geom_b else -1), c.dist) for c in d.contact[:d.ncon]]
    touching = dist[:, 0] <= 0
    ours = [(pos[:, i, 0], normal[:, i, 0], dist[i, 0]) for i in np.flatnonzero(touching)]
    return sorted(mj, key=lambda c: c[2]), sorted(ours, key=lambda c: c[2]), group.kind


def _matched(contact, others, tol=ROUNDOFF):
    """Whether ``contact`` equals one of ``others`` in point, normal and distance, within ``tol`` (round-off)."""
    return any(all(np.abs(np.subtract(x, y)).max() < tol for x, y in zip(contact, other)) for other in others)


def test_hull_vertices_and_planes():
    """The loaded hulls: a cube's 8 corners, their edges and its 6 face planes (its 12 triangles merged), a
    tetrahedron's 4 and 4; the irregular mesh's interior point left out. Every hull vertex is on or below every
    plane and each plane holds at least 3 vertices."""
    xml = _scene("cube", geom_b="irregular", pos_b="1 0 0")
    sys = torchsim.load_mjcf(xml, dtype=F64)
    vert, real, plane = sys.geom_hull_vert, sys.geom_hull_real, sys.geom_hull_plane
    assert real.sum(1).tolist() == [8, 7]
    assert set(map(tuple, plane[0].round(decimals=6).tolist())) == {  # padded by repeats
        (*(s * e for e in np.eye(3)[k]), 0.1) for k in range(3) for s in (-1.0, 1.0)}
    for g in range(2):
        above = vert[g] @ plane[g, :, :3].T - plane[g, :, 3]  # (V, F)
        assert above.max() < 1e-7
        assert ((above[real[g]].abs() < 1e-7).sum(0) >= 3).all()
    # each cube corner's edges: its 3 cube edges (0.2 m along the axes) and the diagonals the triangles add
    for corner, edges in zip(vert[0].numpy(), sys.geom_hull_edge[0].numpy()):
        for edge in -0.2 * np.sign(corner)[:, None] * np.eye(3):
            assert np.abs(edges - edge).max(1).min() < 1e-6
    tet = torchsim.load_mjcf(_scene("tet"), dtype=F64)
    assert tet.geom_hull_real.sum().item() == 4 and len(tet.geom_hull_plane[1].unique(dim=0)) == 4


@pytest.mark.parametrize("mesh, height", [("tet", -0.01), ("cube", 0.06), ("irregular", 0.06)])
def test_mesh_on_plane(mesh, height):
    """A tilted mesh sunk into the floor: every MuJoCo contact (it keeps up to 3 or 4 of the deepest vertices) is
    one of ours, the deepest first; ours are exactly the hull vertices below the floor."""
    xml = _scene(mesh, pos_a=f"0 0 {height}", euler_a="25 -30 20")
    mj, ours, kind = _compare(xml)
    assert kind == "mesh_plane" and mj
    assert all(_matched(c, ours) for c in mj) and _matched(ours[0], mj[:1])
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    mesh_id = m.geom_dataid[1]
    local = m.mesh_vert[m.mesh_vertadr[mesh_id]:m.mesh_vertadr[mesh_id] + m.mesh_vertnum[mesh_id]]
    if mesh == "irregular":
        local = local[:-1]  # the interior point, last
    world = d.geom_xpos[1] + local @ d.geom_xmat[1].reshape(3, 3).T
    hull_below = int((world[:, 2] <= 0).sum())
    assert len(ours) == hull_below > 0


def test_sphere_presses_a_face():
    """A sphere pressed 1 cm into the cube's top face, off its centre: one contact, as MuJoCo's."""
    mj, ours, kind = _compare(_scene("sphere", pos_a="0.02 0.03 0.14", geom_b="cube"))
    assert kind == "sphere_mesh" and len(mj) == len(ours) == 1
    assert _matched(ours[0], mj) and abs(ours[0][2] + 0.01) < 1e-6


def test_capsule_across_a_face():
    """A capsule lying tilted across the cube's top face: its deeper end's contact, as MuJoCo's deepest."""
    mj, ours, kind = _compare(_scene("capsule", pos_a="0.01 0.02 0.125", euler_a="0 80 30", geom_b="cube"))
    assert kind == "capsule_mesh"
    assert _matched(ours[0], mj[:1])


@pytest.mark.parametrize("other, kind", [("box", "box_mesh"), ("cube", "mesh_mesh")])
def test_mesh_face_to_face(other, kind):
    """A cube-shaped mesh sunk 5 mm face down into a box or another such mesh, turned 10 degrees about the normal:
    MuJoCo clips the faces into 4 points (2 corners, 2 edge crossings); ours are the 2 corners, each one of
    MuJoCo's, and the separating-axis contact between the faces, at MuJoCo's depth and normal."""
    mj, ours, loaded = _compare(_scene(other, pos_a="0.02 0.03 0.195", euler_a="0 0 10", geom_b="cube"))
    assert loaded == kind and len(mj) == 4 and len(ours) == 3
    assert sum(_matched(c, mj) for c in ours) == 2
    assert all(abs(c[2] - mj[0][2]) < ROUNDOFF and np.abs(c[1] - mj[0][1]).max() < ROUNDOFF for c in ours)


@pytest.mark.parametrize("other", ["box", "cube"])
def test_edges_crossing(other):
    """Two cubes (a box or a mesh below) crossed edge on edge, 5 mm deep, no vertex of either inside the other:
    the vertices find nothing, the separating axis of the two edges does, at MuJoCo's depth, normal and point."""
    mj, ours, _ = _compare(_scene(other, pos_a=f"0 0 {0.2 * 2 ** 0.5 - 0.005}", euler_a="45 0 0",
                                  geom_b="cube", euler_b="0 45 0"))
    assert len(mj) == len(ours) == 1
    assert abs(ours[0][2] + 0.005) < 1e-6 and _matched(ours[0], mj)


@pytest.mark.parametrize("euler, count", [("90 0 20", 2), ("0 0 0", 4)])
def test_cylinder_on_a_face(euler, count):
    """A cylinder sunk 2 mm into the cube mesh's top face, on its side (MuJoCo's 2 contacts, ours the same) or on
    its cap (4 rim points each, at other angles: the same depth and normal, on the rim); and the separating-axis
    contact between them (mid-side, mid-cap)."""
    mj, ours, kind = _compare(_scene("cylinder", pos_a=f"0.02 0.03 {0.138 if count == 4 else 0.148}",
                                     euler_a=euler, geom_b="cube"))
    assert kind == "cylinder_mesh" and len(mj) == count and len(ours) == count + 1
    assert all(abs(c[2] + 0.002) < 1e-6 and np.abs(c[1] - [0, 0, 1]).max() < ROUNDOFF for c in ours)
    # MuJoCo's side points: 1 um along the axis (its convex solver's tolerance)
    on_rim = [abs(np.hypot(c[0][0] - 0.02, c[0][1] - 0.03) - 0.05) < 1e-9 for c in ours]
    assert sum(_matched(c, mj, tol=1e-6) for c in ours) == 2 if count == 2 else sum(on_rim) == 4
    (middle,) = [c for c, rim in zip(ours, on_rim) if not rim and not _matched(c, mj, tol=1e-6)]
    assert np.abs(middle[0][:2] - [0.02, 0.03]).max() < 1e-9  # the separating-axis contact: mid-side, mid-cap


def test_tilted_cylinder_on_a_face():
    """Tilted 3 degrees on its cap: the deepest rim point is 0.04 cos 3 + 0.05 sin 3 below the centre, as deep as
    MuJoCo's distance (its clipped contact polygon's points lie shallower)."""
    xml = _scene("cylinder", pos_a="0.02 0.03 0.138", euler_a="3 0 0", geom_b="cube")
    _, ours, _ = _compare(xml)
    exact = 0.138 - 0.04 * np.cos(np.radians(3)) - 0.05 * np.sin(np.radians(3)) - 0.1
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    assert abs(ours[0][2] - exact) < 1e-6 and abs(mujoco.mj_geomDistance(m, d, 0, 1, 1.0, None) - exact) < 1e-6


def _sampled(geom_a, geom_b, count=300, band=(-0.01, 0.02), seed=0, **options):
    """MuJoCo's ``mj_geomDistance`` and ours (the smallest over the pair's points) on random poses with MuJoCo's
    distance in ``band`` [m]; ``options``: ``load_mjcf``'s."""
    xml = _scene(geom_a, geom_b=geom_b, pos_b="0 0 1")
    m = mujoco_model(xml, options.get("max_hull_vertices"))
    d = mujoco.MjData(m)
    rng = np.random.default_rng(seed)
    reach = m.geom_rbound[0] + m.geom_rbound[1]
    poses, mj = [], []
    while len(poses) < count:
        q = np.zeros(m.nq)
        for body in range(2):
            quat = rng.normal(size=4)
            q[7 * body + 3:7 * body + 7] = quat / np.linalg.norm(quat)
        q[7:10] = rng.uniform(-reach, reach, 3)
        d.qpos[:] = q
        mujoco.mj_kinematics(m, d)
        dist = mujoco.mj_geomDistance(m, d, 0, 1, 1.0, None)
        if band[0] < dist < band[1]:
            poses.append(q)
            mj.append(dist)
    _, _, _, dist = _ours(xml, np.array(poses), **options)
    return np.array(mj), dist.min(0)


@pytest.mark.parametrize("geom_a", ["sphere", "capsule"])
def test_round_shapes_never_too_shallow(geom_a):
    """A sphere's or capsule's distance from a hull is its largest face-plane distance: never more than MuJoCo's
    (1 um: the capsule's bisection, 2^-11 of its 16 cm segment is 78 um at most, and MuJoCo's tolerance), exact
    where the contact is on a face, short by up to the gap past an edge or vertex. Measured on the irregular
    hull, 300 poses from 1 cm inside to 2 cm apart: the sphere within 1e-9 m of MuJoCo on 35 % of them (the
    capsule on 27 %), short by up to 27 mm (18 mm) elsewhere, where the poses' nearest features are the hull's
    sharp corners."""
    mj, ours = _sampled(geom_a, "irregular")
    short = mj - ours
    assert short.min() > -1e-6
    assert (np.abs(short) < 1e-6).mean() > 0.1  # face contacts: exact
    assert short.max() < 0.03  # past an edge or corner: at most the 2 cm band plus the 1 cm


@pytest.mark.parametrize("geom_a, exact", [("box", 0.85), ("cube", 0.8), ("tet", 0.65), ("irregular", 0.7),
                                            ("cylinder", 0.4)])
def test_hulls_never_too_shallow(geom_a, exact):
    """A box's, hull's or cylinder's distance from a hull (the separating-axis contact and the points): never more
    than MuJoCo's, exact (1 um) where the deepest overlap or the gap is along a face normal or an edge pair at the
    support vertices, short elsewhere. Measured against the irregular hull, 300 poses from 1 cm inside to 2 cm
    apart: exact on 91 % (box), 88 % (cube mesh), 73 % (tetrahedron), 78 % (irregular), 47 % (cylinder); short at
    the 90th percentile by 0, 0.3, 4.4, 2.0 and 6.4 mm, at most by 21, 21, 35, 11 and 21 mm."""
    mj, ours = _sampled(geom_a, "irregular")
    short = mj - ours
    assert short.min() > -1e-6
    assert (np.abs(short) < 1e-6).mean() > exact


# an ellipsoid dropped tilted onto a cube mesh fixed in the world, turned 20 degrees
EGG_ON_CUBE = f"""<mujoco><option timestep="0.002"/><asset><mesh name="cube" vertex="{CUBE}"/></asset><worldbody>
  <geom type="mesh" mesh="cube" euler="0 0 20"/>
  <body pos="0.01 0.02 0.14" euler="8 -5 0"><freejoint/><geom type="ellipsoid" size="0.05 0.04 0.03"/></body>
</worldbody></mujoco>"""


@pytest.mark.parametrize("scene", ["irregular_on_floor", "egg_on_cube"])
@pytest.mark.parametrize("method", METHODS)
def test_drop_comes_to_rest(method, scene):
    """The irregular mesh dropped 2 cm onto the floor, or an ellipsoid 1 cm onto a cube mesh, tilted, falls and
    rests at MuJoCo's height and attitude: within 1 mm (MuJoCo's soft contact rests ~0.1-0.4 mm deep, the spring
    method's up to 0.75 mm, XPBD on the surface: as ``test_round_geoms``) and 1 degree (measured for the ellipsoid:
    0.4 mm and 0.6-0.7 degrees); a wrong hull face or vertex moves it by centimetres."""
    xml = (EGG_ON_CUBE if scene == "egg_on_cube" else
           _scene("irregular", pos_a="0 0 0.12", euler_a="8 -5 0").replace('gravity="0 0 0"', 'timestep="0.002"'))
    mj, ours = (q[:7] for q in rest_pose(xml, method, seconds=0.6))
    assert abs(mj[2] - ours[2]) < 1e-3
    turn = 2 * np.degrees(np.arccos(min(1.0, abs(float(np.dot(mj[3:7], ours[3:7]))))))
    assert turn < 1.0, turn


def test_kernel_runs_a_mesh_scene():
    """The generated C++ step (``kernel`` strategy) on a tetrahedron sunk 2 mm into the floor, a second one on it,
    a capsule across that one's apex and an ellipsoid 1.7 mm into its side, each mesh pair touching from the start:
    the same states as the reference step, by test_strategies' bound."""
    from test_strategies import _check_against_reference

    xml = SCENE.format(tet=TET, cube=CUBE, irr=IRREGULAR, ball=BALL, floor=FLOOR, pos_a="0 0 0.015", euler_a="10 5 0",
                       geom_a=GEOMS["tet"], body_b=(
                           '<body pos="-0.02 -0.03 0.21" euler="4 0 10"><freejoint/><geom type="mesh" mesh="tet"/>'
                           '</body><body pos="0.02 0.02 0.415" euler="0 90 0"><freejoint/>'
                           '<geom type="capsule" size="0.03 0.08"/></body><body pos="-0.06 -0.03 0.21" euler="0 30 0">'
                           '<freejoint/><geom type="ellipsoid" size="0.05 0.04 0.03"/></body>')
                       ).replace('gravity="0 0 0"', "")
    sys = torchsim.load_mjcf(xml, dtype=F64)
    start = torchsim.init(sys, sys.q0[None].repeat(2, 1), 0.2 * torch.randn(2, sys.nv, dtype=F64,
                                                                          generator=torch.Generator().manual_seed(0)))
    depth = contacts(sys, with_world(*(lanes.to_lanes(x, 1) for x in start[:4]))).depth[:, 0]
    touching = {g.kind for g, d in zip(sys.contact_groups, depth.split(
        [points_per_pair(g.kind, sys.geom_hull_vert.shape[1]) * len(g.geom_a) for g in sys.contact_groups])) if d.max() > 0}
    assert touching == {"mesh_plane", "mesh_mesh", "capsule_mesh", "ellipsoid_mesh"}
    stepper = torchsim.Stepper(sys, "kernel", threads=1)
    _check_against_reference("mesh scene kernel", sys, stepper, start, torch.zeros(20, 2, 0, dtype=F64), 2, 1e-3)
    assert stepper.strategy == "kernel"  # no fallback


def test_large_hull_refused_by_name():
    """A mesh whose hull has more vertices than the bound is refused naming the geom, its count, the bound and both
    caps (the load option, MuJoCo's ``maxhullvert``); with either it loads, the option capping that mesh alone and
    saying so once; a cap above the bound is refused."""
    xml = _scene("sphere", geom_b="ball", pos_b="1 0 0")
    with pytest.raises(UnsupportedMJCFError, match=f"'b' can collide and its convex hull has 100 vertices, more "
                                                   f"than the {MAX_HULL_VERTICES}.*max_hull_vertices=.*maxhullvert"):
        torchsim.load_mjcf(xml)
    sys = torchsim.load_mjcf(xml.replace('<mesh name="ball"', f'<mesh name="ball" maxhullvert="{MAX_HULL_VERTICES}"'))
    assert sys.geom_hull_real.sum().item() == MAX_HULL_VERTICES
    with pytest.warns(UserWarning) as caught:
        sys = torchsim.load_mjcf(xml, max_hull_vertices=40)
    (warning,) = [w for w in caught if "max_hull_vertices" in str(w.message)]
    assert "caps the convex hulls of 1 colliding meshes (their vertices before): 'ball' (100)" in str(warning.message)
    assert sys.geom_hull_real.sum().item() == 40
    m = mujoco_model(xml, 40)
    assert m.mesh_graph[m.mesh_graphadr[3]] == 40 and m.mesh_graph[m.mesh_graphadr[2]] == 7  # the irregular: as it was
    for bad in (MAX_HULL_VERTICES + 1, 3, 20.0, True):
        with pytest.raises(ValueError, match="max_hull_vertices must be an integer from 4"):
            torchsim.load_mjcf(xml, max_hull_vertices=bad)


def test_capped_hull_on_plane():
    """The ball capped at 64 hull vertices, tilted and sunk 1 cm into the floor: MuJoCo's contacts (on the capped
    model) are ours, ours exactly the capped hull's vertices below the floor, to round-off."""
    xml = _scene("ball", pos_a="0 0 0.09", euler_a="25 -30 20")
    mj, ours, kind = _compare(xml, max_hull_vertices=MAX_HULL_VERTICES)
    assert kind == "mesh_plane" and mj
    assert all(_matched(c, ours) for c in mj) and _matched(ours[0], mj[:1])
    m = mujoco_model(xml, MAX_HULL_VERTICES)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    mesh = m.geom_dataid[1]
    adr, numvert = m.mesh_graphadr[mesh], m.mesh_graph[m.mesh_graphadr[mesh]]
    hull = m.mesh_vert[m.mesh_vertadr[mesh] + m.mesh_graph[adr + 2 + numvert:adr + 2 + 2 * numvert]]
    world = d.geom_xpos[1] + hull @ d.geom_xmat[1].reshape(3, 3).T
    assert numvert == MAX_HULL_VERTICES and len(ours) == int((world[:, 2] <= 0).sum()) > 0


def test_capped_hull_against_box():
    """A box pressed into the capped ball: MuJoCo's deepest contact on the capped model is one of ours (1 um, its
    solver's tolerance); and on 300 sampled poses from 1 cm inside to 2 cm apart the box's distance from the capped
    hull is never more than MuJoCo's ``mj_geomDistance`` on that model (1 um), and exact (1 um) on most, as
    ``test_hulls_never_too_shallow`` (measured: exact on 92 %, short by at most 5.8 mm)."""
    mj, ours, kind = _compare(_scene("box", pos_a="0.02 0.03 0.195", euler_a="10 20 30", geom_b="ball"),
                              max_hull_vertices=MAX_HULL_VERTICES)
    assert kind == "box_mesh" and mj
    assert _matched(mj[0], ours, tol=1e-6)
    mj, ours = _sampled("box", "ball", max_hull_vertices=MAX_HULL_VERTICES)
    short = mj - ours
    assert short.min() > -1e-6
    assert (np.abs(short) < 1e-6).mean() > 0.5


def test_ellipsoid_presses_a_face():
    """An ellipsoid tilted and pressed 8 mm into the cube's top face: one contact, at MuJoCo's distance and normal
    (1 um, 1e-5: its convex solver's tolerance), at the ellipsoid's lowest point lifted half the depth (1e-9 m)."""
    xml = _scene("ellipsoid", pos_a="0.02 0.03 0.125", euler_a="10 20 0", geom_b="cube")
    mj, ours, kind = _compare(xml)
    assert kind == "ellipsoid_mesh" and len(mj) == len(ours) == 1
    (_, mj_normal, mj_dist), (pos, normal, dist) = mj[0], ours[0]  # MuJoCo's point: its solver's, 8e-5 m off
    assert abs(dist - mj_dist) < 1e-6 and np.abs(normal - mj_normal).max() < 1e-5
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    rot, semi = d.geom_xmat[0].reshape(3, 3), m.geom_size[0]
    down = semi * (rot.T @ [0, 0, -1.0])  # the support point along -z: R S^2 R^T d / |S R^T d|
    lowest = d.geom_xpos[0] + rot @ (semi * down / np.linalg.norm(down))
    assert abs(dist - (lowest[2] - np.float32(0.1))) < ROUNDOFF  # the top face, at the float32 vertices' height
    assert np.abs(pos - (lowest - [0, 0, 0.5 * dist])).max() < ROUNDOFF and np.abs(normal - [0, 0, 1]).max() < ROUNDOFF


@pytest.mark.parametrize("hull, options", [("irregular", {}), ("tet", {}), ("cube", {}),
                                           ("ball", dict(max_hull_vertices=MAX_HULL_VERTICES))])
def test_ellipsoid_never_too_shallow(hull, options):
    """An ellipsoid's distance from a hull (its separating-axis contact over the faces' normals and the ellipsoid's
    normals nearest the vertices and the edges at the nearest vertex): never more than MuJoCo's (1 um), exact (1 um)
    where the nearest feature is a face, a vertex or an edge at the nearest vertex. Measured, 300 poses from 1 cm
    inside to 2 cm apart: exact on 99 % (irregular), 100 % (tetrahedron, cube), 99 % (ball capped at 64 vertices);
    short at most by 2.8 mm (irregular, 1 pose, 1 cm deep) and 14 um (ball)."""
    mj, ours = _sampled("ellipsoid", hull, **options)
    short = mj - ours
    assert short.min() > -1e-6
    assert (np.abs(short) < 1e-6).mean() > 0.95
