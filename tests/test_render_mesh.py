"""Mesh geoms in torchsim.render: BVH ray casting against brute force, and depth and segmentation
against MuJoCo's own renderer.

MuJoCo's images come from ``mujoco.Renderer`` in a child process (``MUJOCO_GL=egl``, ``osmesa`` as a fallback;
skipped where neither gives a GL context), through ``tests/test_render.py``'s helper. Criteria as there: a depth
pixel agrees when within 1 cm or 0.5% of MuJoCo's depth (depth-buffer quantisation and float32 rounding are far
below that; a silhouette pixel whose centre lies within rounding of a triangle's edge may see the triangle in one
renderer and the background in the other, which no depth tolerance hides: those pixels are what the thresholds
leave room for: 0.2% of pixels, 18 per camera over 3 states at 64x48). Both renderers draw the same triangles and
sample pixel centres, so, unlike round primitives, there is no tessellation residue: measured agreement is 100% of
pixels (see each test). The tests can fail: every mesh's vertices moved 2 mm sideways fail the inline scene's arm
camera (depth 99.70%) and the Panda (99.57% depth, 99.20% segmentation); 5 mm fail every camera (98.4-99.7%).
"""

import pathlib
import warnings

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from test_render import fmt, mujoco_images, random_q, xyaxes
from torchsim.render import Camera, Scene, render
from torchsim.render import mesh as mesh_bvh
from torchsim.render.viewer import scene_geom_mesh

H, W = 48, 64
STATES = 3


def icosphere(radius: float, subdivisions: int = 1):
    """Vertices and outward triangles of an icosahedron subdivided ``subdivisions`` times, on a sphere."""
    p = (1 + 5 ** 0.5) / 2
    v = [(-1, p, 0), (1, p, 0), (-1, -p, 0), (1, -p, 0), (0, -1, p), (0, 1, p), (0, -1, -p), (0, 1, -p),
         (p, 0, -1), (p, 0, 1), (-p, 0, -1), (-p, 0, 1)]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2), (10, 7, 6),
         (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10),
         (8, 6, 7), (9, 8, 1)]
    v = [np.array(x, float) / np.linalg.norm(x) for x in v]
    for _ in range(subdivisions):
        mid, faces = {}, []

        def middle(a, b):
            key = (min(a, b), max(a, b))
            if key not in mid:
                m = v[a] + v[b]
                v.append(m / np.linalg.norm(m))
                mid[key] = len(v) - 1
            return mid[key]
        for a, b, c in f:
            ab, bc, ca = middle(a, b), middle(b, c), middle(c, a)
            faces += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        f = faces
    return np.array(v) * radius, np.array(f)


BALL_V, BALL_F = icosphere(0.2, 2)  # 320 triangles: a BVH of depth 7
#: A floor, a tetrahedron (scaled) and an icosphere on free bodies, a box given by its 8 corners (MuJoCo makes the
#: triangles: its hull) on a hinged arm with a capsule, the ball coloured by a material (visual only: its hull is
#: more than torchsim collides); a world camera and a
#: camera carried by the arm.
MESHES_XML = f"""<mujoco><asset>
  <mesh name="tet" vertex="0 0 0 1 0 0 0 1 0 0 0 1" scale="0.4 0.3 0.5"/>
  <mesh name="cube" vertex="-1 -1 -1 1 -1 -1 -1 1 -1 1 1 -1 -1 -1 1 1 -1 1 -1 1 1 1 1 1" scale="0.15 0.1 0.2"/>
  <mesh name="ball" vertex="{fmt(BALL_V.ravel())}" face="{' '.join(map(str, BALL_F.ravel()))}"/>
  <material name="blue" rgba="0.1 0.2 0.9 1"/>
</asset><worldbody>
  <geom name="floor" type="plane" size="2 2 0.1" rgba="0.8 0.8 0.7 1"/>
  <camera name="world" pos="1.4 -1.6 1.3" xyaxes="{fmt(xyaxes((1.4, -1.6, 1.3), (0.1, 0.0, 0.3)))}" fovy="50"/>
  <body name="tetra" pos="-0.1 -0.2 0.3" euler="10 20 30"><freejoint/>
    <geom name="tetra" type="mesh" mesh="tet" rgba="0.9 0.2 0.1 1"/></body>
  <body name="ball" pos="-0.45 0.35 0.35"><freejoint/><geom name="ball" type="mesh" mesh="ball" material="blue"
    contype="0" conaffinity="0"/></body>
  <body name="arm" pos="0.5 0.1 0.45"><joint name="hinge" type="hinge" axis="0 1 0"/>
    <geom name="rod" type="capsule" fromto="0 0 0 0.25 0 0" size="0.04"/>
    <geom name="cube" type="mesh" mesh="cube" pos="0.35 0 0" euler="0 0 25" rgba="0.2 0.8 0.3 1"/>
    <camera name="onarm" pos="0.6 -0.9 0.5" xyaxes="{fmt(xyaxes((0.6, -0.9, 0.5), (-0.3, 0.1, -0.2)))}" fovy="60"/>
  </body>
</worldbody></mujoco>"""

PANDA = pathlib.Path.home() / ".cache/torchsim/third_party/robosuite-1.5.2-py3-none-any/robosuite/models/assets" \
    / "robots/panda/robot.xml"


def panda_xml():
    """robosuite's Panda arm (its 50 visual meshes, 0.14 M triangles; the 8 collision meshes moved to group 3,
    hidden in both renderers, as they coincide with the visual ones) with a floor and a world camera."""
    xml = PANDA.read_text()
    eye, target = (0.85, -0.85, 0.75), (0.0, 0.0, 0.45)
    xml = xml.replace('<compiler angle="radian"/>', f'<compiler angle="radian" meshdir="{PANDA.parent}"/>')
    xml = xml.replace('group="0" mesh=', 'group="3" mesh=')
    return xml.replace("<worldbody>", f'<worldbody><geom name="floor" type="plane" size="1 1 0.1" rgba="0.6 0.6 0.6 1"/>'
                       f'<camera name="world" pos="{fmt(eye)}" xyaxes="{fmt(xyaxes(eye, target))}" fovy="45"/>', 1)


def scene_and_states(xml, states=STATES, seed=0, **load):
    m = mujoco.MjModel.from_xml_string(xml)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the Panda's hull caps (a physics note)
        system = torchsim.load_mjcf(xml, **load)
    q = torch.as_tensor(random_q(m, states, seed), dtype=system.dtype)
    return m, Scene.build(m, system), torchsim.init(system, q, torch.zeros(states, system.nv, dtype=system.dtype))


def agreement(xml, cameras, **load):
    """Fractions of pixels (per camera) where torchsim's depth agrees with MuJoCo's and where both see the same
    geom, the fraction MuJoCo sees any mesh geom, and the p99 depth error where both see the same geom."""
    m, scene, state = scene_and_states(xml, **load)
    ours = render(scene, state, list(cameras), H, W)
    (depth_ref, seg_ref), = mujoco_images([(xml, state.q.double().numpy(), tuple(cameras), H, W)])
    depth, seg = ours.depth.numpy(), ours.segmentation.numpy()
    close = np.abs(depth - depth_ref) <= np.maximum(0.01, 0.005 * depth_ref)
    meshes = np.flatnonzero(m.geom_type == mujoco.mjtGeom.mjGEOM_MESH)
    both = (seg == seg_ref) & (seg_ref >= 0)
    return (close.mean((0, 2, 3)), (seg == seg_ref).mean((0, 2, 3)), np.isin(seg_ref, meshes).mean((0, 2, 3)),
            np.percentile(np.abs(depth - depth_ref)[both], 99))


# ---------------------------------------------------------------------------------------------- the BVH itself
def brute_force(vert, face, o, d, znear, zfar):
    """Nearest ``t`` of every ray against every triangle (float64 numpy Möller-Trumbore, both faces)."""
    v0, v1, v2 = (vert[face[:, i]] for i in range(3))
    e1, e2 = v1 - v0, v2 - v0
    p = np.cross(d[:, None], e2[None])
    det = (e1[None] * p).sum(-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = o[:, None] - v0[None]
        u = (s * p).sum(-1) / det
        q = np.cross(s, e1[None])
        v = (d[:, None] * q).sum(-1) / det
        t = (e2[None] * q).sum(-1) / det
    ok = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > znear) & (t < zfar)
    return np.where(ok, t, np.inf).min(1)


def test_bvh_hits_what_brute_force_hits():
    """Rays through a mesh of 320 triangles (a tree 7 levels deep) and a tetrahedron (one leaf: its traversal starts
    7 levels later) find the nearest triangle that testing every triangle finds (float64)."""
    m = mujoco.MjModel.from_xml_string(MESHES_XML)
    ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_MESH, n) for n in ("ball", "tet")]
    meshes = mesh_bvh.build(m, ids)
    assert meshes.depth == 7 and meshes.start.tolist() == [0, 7]
    rng = np.random.default_rng(1)
    for k in range(2):
        vert, face = meshes.geometry(k)
        radius = np.linalg.norm(vert, axis=1).max()
        o = rng.normal(size=(3000, 3))
        o = 2 * radius * o / np.linalg.norm(o, axis=1, keepdims=True)
        d = rng.uniform(-1.2, 1.2, (3000, 3)) * radius - o  # towards the middle, missing it now and then
        t, tri = mesh_bvh.cast(meshes, torch.full((3000,), k), torch.as_tensor(o), torch.as_tensor(d), 0.01, 10.0,
                               want_tri=True)
        expect = brute_force(vert, face, o, d, 0.01, 10.0)
        assert 0.1 < np.isfinite(expect).mean() < 0.9, np.isfinite(expect).mean()
        np.testing.assert_allclose(t.numpy(), expect, rtol=1e-9, atol=1e-12)
        hit = torch.isfinite(t)
        assert (tri[hit] >= 0).all() and (tri[~hit] == -1).all()
        # told a surface lies at the nearest hit (or halfway), a ray still finds it (or anything beyond the bound)
        for scale in (1.0, 0.5):
            limit = torch.as_tensor(np.where(np.isfinite(expect), scale * expect, 10.0))
            bounded, _ = mesh_bvh.cast(meshes, torch.full((3000,), k), torch.as_tensor(o), torch.as_tensor(d), 0.01,
                                       10.0, limit=limit)
            assert (bounded[hit] == t[hit]).all() if scale == 1.0 else (bounded[hit] > limit[hit]).all()
        # the triangle found is one at that depth: its face normal is along the hit point's offset on the sphere
        if k == 0:
            point = o[hit.numpy()] + t[hit].numpy()[:, None] * d[hit.numpy()]
            cos = (meshes.normal[tri[hit]].numpy() * point).sum(1) / np.linalg.norm(point, axis=1)
            assert cos.min() > 0.97


def test_mesh_box_renders_as_the_box_primitive():
    """A box given as a mesh (its 8 corners; MuJoCo makes the triangles and re-poses the mesh frame) and the box
    primitive of the same size and pose give the same depth (to 1e-6 where both hit in float64: MuJoCo stores
    vertices in float32; 1e-4 in float32; silhouettes the same but for pixels through an edge) and the same lambert
    colour (the face normals, found by a second cast near the drawn depth)."""
    corners = np.stack(np.meshgrid([-0.3, 0.3], [-0.2, 0.2], [-0.1, 0.1], indexing="ij"), -1).reshape(-1, 3)
    geom = 'euler="10 20 30" rgba="0.5 0.6 0.7 1" contype="0" conaffinity="0"'
    shapes = (f'<geom type="box" size="0.3 0.2 0.1" {geom}/>', f'<geom type="mesh" mesh="m" {geom}/>')
    cams = [Camera.look_at((0.9, -0.7, 0.6), (0, 0, 0), fovy=40.0), Camera.look_at((0, 0, 1), (0, 0, 0), up=(0, 1, 0))]
    for dtype, tol in ((torch.float64, 1e-6), (torch.float32, 1e-4)):  # float64: MuJoCo's float32 vertices
        images = []
        for shape in shapes:
            xml = (f'<mujoco><asset><mesh name="m" vertex="{fmt(corners.ravel())}"/></asset><worldbody>'
                   f'<body pos="0.05 0 0"><freejoint/>{shape}</body></worldbody></mujoco>')
            system = torchsim.load_mjcf(xml, dtype=dtype)
            state = torchsim.init(system, system.q0[None], torch.zeros(1, system.nv, dtype=dtype))
            scene = Scene.build(mujoco.MjModel.from_xml_string(xml), system)
            images.append(render(scene, state, cams, 40, 50, rgb=True))
        a, b = images
        both = (a.segmentation >= 0) & (b.segmentation >= 0)
        assert both.double().mean() > 0.1
        assert (a.segmentation == b.segmentation).double().mean() > 0.995
        torch.testing.assert_close(a.depth[both], b.depth[both], atol=tol, rtol=0)
        torch.testing.assert_close(a.rgb[both], b.rgb[both], atol=tol, rtol=0)  # the shading normals too


# ----------------------------------------------------------------------------------------- against MuJoCo's renderer
def test_meshes_agree_with_mujoco_renderer():
    """Tetrahedron, box (MuJoCo's hull of 8 corners) and icosphere meshes on free and hinged bodies, a world camera
    and one carried by the arm, 3 random states, 64x48 (measured: depth and segmentation agree on 100% of the pixels of both cameras; p99 depth
    error 1.4e-6 m where both see the same geom)."""
    close, same, seen, p99 = agreement(MESHES_XML, ("world", "onarm"))
    assert (seen > 0.03).all(), f"the meshes are hardly in view: {seen}"
    assert (close >= 0.998).all(), f"depth agrees on {close} of pixels"
    assert (same >= 0.998).all(), f"segmentation agrees on {same} of pixels"
    assert p99 < 1e-3


@pytest.mark.skipif(not PANDA.exists(), reason=f"robosuite's Panda is not in the third-party cache ({PANDA}; "
                    "studies/check_robot_models.py --packages robosuite fetches it)")
def test_panda_agrees_with_mujoco_renderer():
    """robosuite's Panda (50 visual meshes, 0.14 M triangles) at 3 random poses (measured: depth and
    segmentation agree on 100% of pixels; p99 depth error 5e-7 m)."""
    close, same, seen, p99 = agreement(panda_xml(), ("world",), max_hull_vertices=64)
    assert seen[0] > 0.05, f"the robot is hardly in view: {seen}"
    assert close[0] >= 0.998, f"depth agrees on {close[0]:.2%} of pixels"
    assert same[0] >= 0.998, f"segmentation agrees on {same[0]:.2%} of pixels"
    assert p99 < 1e-3


# ------------------------------------------------------------------------------------------- paths and colours
def test_tiles_dense_and_colour():
    """Culling by tiles and testing every pixel give the same mesh images; a mesh takes its rgba or its material's
    colour, and a face square to the headlight its full colour."""
    m, scene, state = scene_and_states(MESHES_XML)
    cams = ["world", "onarm"]
    tiled = render(scene, state, cams, H, W, rgb=True)
    dense = render(scene, state, cams, H, W, rgb=True, tile=0)
    for a, b in zip(tiled, dense):
        assert torch.equal(a, b)
    ball = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "ball")
    k = scene.geom_id.tolist().index(ball)
    assert scene.geom_type[k] == "mesh"
    torch.testing.assert_close(scene.geom_rgba[k], torch.tensor([0.1, 0.2, 0.9, 1.0], dtype=torch.float64))
    # straight down onto the cube's top face (the arm at rest): lambert factor 1
    cube = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "cube")
    system = torchsim.load_mjcf(MESHES_XML)
    rest = torchsim.init(system, system.q0[None], torch.zeros(1, system.nv))
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    top = Camera.look_at(d.geom_xpos[cube] + np.array([0, 0, 1.0]), d.geom_xpos[cube], up=(0, 1, 0), fovy=10)
    image = render(scene, rest, top, 9, 9, rgb=True)
    assert image.segmentation[0, 4, 4] == cube
    torch.testing.assert_close(image.rgb[0, 4, 4], torch.tensor([0.2, 0.8, 0.3]), atol=1e-5, rtol=0)
    assert abs(image.depth[0, 4, 4] - 0.8) < 1e-4  # 1 m above the centre, the top face 0.2 m up


def test_viewer_takes_the_mesh_triangles():
    m, scene, _ = scene_and_states(MESHES_XML, states=1)
    k = scene.geom_id.tolist().index(mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "ball"))
    vertices, faces = scene_geom_mesh(scene, k)
    dataid = m.geom_dataid[scene.geom_id[k]]
    va, vn = m.mesh_vertadr[dataid], m.mesh_vertnum[dataid]
    np.testing.assert_allclose(vertices, m.mesh_vert[va:va + vn], atol=1e-7)
    assert faces.shape == (m.mesh_facenum[dataid], 3) and faces.max() < vn


def test_viewer_draws_the_meshes():
    """The browser viewer builds a scene with mesh geoms (their own triangles, in their bodies' frames) and
    records it."""
    pytest.importorskip("viser", reason="viser not installed (pip install viser)")
    from torchsim.render.viewer import Viewer

    m, scene, state = scene_and_states(MESHES_XML, states=1)
    viewer = Viewer(scene, host="127.0.0.1", port=8791, verbose=False)
    try:
        viewer.update(state)
        assert len(viewer.to_html(state, 0.05)) > 10_000
    finally:
        viewer.close()
