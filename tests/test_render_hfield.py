"""Height fields in torchsim.render: the triangulation, and depth and segmentation against MuJoCo's own renderer.

A height field is triangulated once at scene build as MuJoCo's renderer draws it (``mjr_uploadHField``: the grid's
cells split along the diagonal from ``(row, col)`` to ``(row + 1, col + 1)``, four side walls down to the base
elevation ``-size[3]``, a bottom) and drawn through the mesh path's BVH (:mod:`torchsim.render.hfield`).

MuJoCo's images and the criteria are ``tests/test_render_mesh.py``'s (after ``tests/test_render.py``): a depth pixel
agrees within 1 cm or 0.5%; thresholds 99.8% of pixels per camera for depth and for segmentation (the room left for
pixel centres within rounding of a triangle's edge, where one renderer sees the surface and the other grazes past:
MuJoCo's vertices are float32). Both draw the same triangles, so agreement is 100% but for such pixels (see each
test). The tests can fail, checked by breaking the triangulation on purpose: the cells split along the other
diagonal fail both scenes (depth 91.2% inline, 99.67% on the quadruped's terrain), the field without its walls and
bottom fails the inline one (89.2%), the field moved 2 mm sideways fails it too (depth 98.9%).
"""

import pathlib
import warnings
import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from test_render import fmt, mujoco_images, random_q, xyaxes
from torchsim.render import Camera, Scene, render
from torchsim.render import hfield as hfield_mesh
from torchsim.render.viewer import scene_geom_mesh

H, W = 48, 64
STATES = 3

NROW, NCOL = 12, 16
_R, _C = np.mgrid[0:NROW, 0:NCOL]
#: A slope along +x with bumps, in 0..1 (MuJoCo's ``hfield_data`` is the ``elevation`` as given).
ELEVATION = 0.3 + 0.4 * _C / (NCOL - 1) + 0.25 * np.sin(1.1 * _R) * np.cos(0.9 * _C)
ELEVATION = (ELEVATION - ELEVATION.min()) / np.ptp(ELEVATION)
EYE, TARGET = (1.9, -1.6, 1.4), (0.0, 0.1, 0.1)
#: A 12 x 16 field (1.2 x 0.9 m half sizes, 0.35 m high, base 0.15 m below) turned and offset, a free ball above
#: it, and an oblique camera that sees its surface, two of its side walls and the ball.
HFIELD_XML = f"""<mujoco><asset><hfield name="terrain" nrow="{NROW}" ncol="{NCOL}" size="1.2 0.9 0.35 0.15"
  elevation="{fmt(ELEVATION.ravel())}"/></asset><worldbody>
  <geom name="terrain" type="hfield" hfield="terrain" pos="0.05 -0.1 0.02" euler="4 -3 20" rgba="0.4 0.6 0.3 1"/>
  <camera name="oblique" pos="{fmt(EYE)}" xyaxes="{fmt(xyaxes(EYE, TARGET))}" fovy="50"/>
  <body name="ball" pos="0.2 0.1 0.8"><freejoint/>
    <geom name="ball" type="sphere" size="0.12" rgba="0.9 0.2 0.1 1"/></body>
</worldbody></mujoco>"""


def scene_and_states(xml, states=STATES, seed=0):
    m = mujoco.MjModel.from_xml_string(xml)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        system = torchsim.load_mjcf(xml, dtype=torch.float64)
    q = torch.as_tensor(random_q(m, states, seed), dtype=system.dtype)
    return m, system, Scene.build(m, system), torchsim.init(system, q, torch.zeros(states, system.nv,
                                                                                  dtype=system.dtype))


def agreement(xml, cameras):
    """Per camera: the fractions of pixels where torchsim's depth agrees with MuJoCo's, where both see the same
    geom, where MuJoCo sees a height field; and the p99 depth error where both see the same height field."""
    m, _, scene, state = scene_and_states(xml)
    ours = render(scene, state, list(cameras), H, W)
    (depth_ref, seg_ref), = mujoco_images([(xml, state.q.double().numpy(), tuple(cameras), H, W)])
    depth, seg = ours.depth.numpy(), ours.segmentation.numpy()
    close = np.abs(depth - depth_ref) <= np.maximum(0.01, 0.005 * depth_ref)
    fields = np.isin(seg_ref, np.flatnonzero(m.geom_type == mujoco.mjtGeom.mjGEOM_HFIELD))
    both = (seg == seg_ref) & fields
    return (close.mean((0, 2, 3)), (seg == seg_ref).mean((0, 2, 3)), fields.mean((0, 2, 3)),
            np.percentile(np.abs(depth - depth_ref)[both], 99))


# ------------------------------------------------------------------------------------------- the triangulation
def test_triangulation_is_mujocos_surface_and_solid():
    """The surface's vertices are MuJoCo's grid (x along columns, y along rows, z = data size_z), each cell split
    along the diagonal from (row, col) to (row + 1, col + 1), normals up; walls and bottom close the solid, wound
    outward (the volume the triangles enclose is the field's above its base)."""
    m = mujoco.MjModel.from_xml_string(HFIELD_XML)
    size = m.hfield_size[0]
    vert, face = hfield_mesh.triangulate(hfield_mesh.elevation(m, 0), size)
    cells = (NROW - 1) * (NCOL - 1)
    assert face.shape == (2 * cells + 4 * (NROW + NCOL - 2) + 2, 3)
    grid = vert[:NROW * NCOL].reshape(NROW, NCOL, 3)
    np.testing.assert_allclose(grid[0, 0], [-size[0], -size[1], m.hfield_data[0] * size[2]])
    np.testing.assert_allclose(grid[NROW - 1, 0, :2], [-size[0], size[1]])  # rows run along +y
    np.testing.assert_allclose(grid[..., 2].ravel(), m.hfield_data * size[2], rtol=1e-6)
    tri = vert[face]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert (normal[:2 * cells, 2] > 0).all()
    diagonal = {tuple(sorted(e)) for e in face[:2 * cells, [0, 2]]}  # the edge each surface triangle's first and last
    index = np.arange(NROW * NCOL).reshape(NROW, NCOL)  # vertices share: the cell's diagonal
    assert {tuple(sorted(e)) for e in zip(index[:-1, :-1].ravel(), index[1:, 1:].ravel())} <= diagonal
    top = face[:-2]  # surface and walls: every edge shared by two triangles but the base rim's (the bottom's)
    edges = np.sort(np.concatenate([top[:, [0, 1]], top[:, [1, 2]], top[:, [2, 0]]]), 1)
    _, count = np.unique(edges, axis=0, return_counts=True)
    assert (count == 2).sum() == len(count) - 2 * (NROW + NCOL - 2) and count.max() == 2
    volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6
    cell_area = (2 * size[0] / (NCOL - 1)) * (2 * size[1] / (NROW - 1))
    z = grid[..., 2]  # the prism volume under the two triangles of each cell, above the base
    expect = cell_area / 6 * ((z[:-1, :-1] + z[1:, :-1] + z[1:, 1:]) + (z[:-1, :-1] + z[:-1, 1:] + z[1:, 1:])).sum()
    assert abs(volume - (expect + 4 * size[0] * size[1] * size[3])) < 1e-9


# ----------------------------------------------------------------------------------------- against MuJoCo's renderer
def test_hfield_agrees_with_mujoco_renderer():
    """The inline field (turned and offset) under a free ball, an oblique camera, 3 random states, 64x48 (measured:
    depth and segmentation agree on 99.97% of pixels, all but one pixel, the same in each state, whose ray grazes
    the field's far rim 1.4e-3 pixel above it; p99 depth error on the field 2.2e-6 m)."""
    close, same, seen, p99 = agreement(HFIELD_XML, ("oblique",))
    assert seen[0] > 0.2, f"the field is hardly in view: {seen}"
    assert close[0] >= 0.998, f"depth agrees on {close[0]:.2%} of pixels"
    assert same[0] >= 0.998, f"segmentation agrees on {same[0]:.2%} of pixels"
    assert p99 < 1e-3


def test_hfield_among_meshes_agrees_with_mujoco_renderer():
    """``tests/test_render_mesh.py``'s mesh scene with a (visual-only) height field poking through its floor: the
    field's BVH and the meshes' share one table (trees of different depths), both cameras (the field covers 6% and 3%
    of their pixels; measured: 100% of depth and segmentation pixels agree)."""
    from test_render_mesh import MESHES_XML, agreement as mesh_agreement

    field = (f'<hfield name="t" nrow="{NROW}" ncol="{NCOL}" size="1.5 1.2 0.2 0.05" '
             f'elevation="{fmt(ELEVATION.ravel())}"/>')
    floor = '<geom name="floor" type="plane" size="2 2 0.1" rgba="0.8 0.8 0.7 1"/>'
    xml = MESHES_XML.replace("<asset>", "<asset>" + field).replace(
        floor, floor + '<geom name="terrain" type="hfield" hfield="t" pos="0 0 -0.15" contype="0" conaffinity="0"/>')
    close, same, _, p99 = mesh_agreement(xml, ("world", "onarm"))
    assert (close >= 0.998).all(), f"depth agrees on {close} of pixels"
    assert (same >= 0.998).all(), f"segmentation agrees on {same} of pixels"
    assert p99 < 1e-3


def _dm_control_suite():
    import importlib.util

    spec = importlib.util.find_spec("dm_control")
    roots = [pathlib.Path(spec.origin).parent] if spec else []
    roots += sorted(pathlib.Path.home().glob(".cache/torchsim/third_party/dm_control-*/dm_control"))
    for root in roots:
        if (root / "suite" / "quadruped.xml").is_file():
            return root / "suite"
    pytest.skip("dm_control's quadruped.xml is not installed (nor cached by studies/check_third_party.py)")


def quadruped_xml():
    """dm_control's quadruped as its escape task builds it (terrain kept; walls, ball and target removed), its
    201 x 201 terrain filled in as the task does at run time (a bowl times smooth random bumps; here bilinear
    bumps from a fixed seed), its sites and rangefinders hidden (MuJoCo draws sites and the rangefinders' rays,
    torchsim neither), and a world camera."""
    suite = _dm_control_suite()
    root = ET.fromstring((suite / "quadruped.xml").read_text())
    for include in root.iter("include"):
        include.set("file", str(suite / include.get("file")))
    world = root.find("worldbody")
    for name in ("wall_px", "wall_py", "wall_nx", "wall_ny", "target", "ball"):
        element = next(e for e in world if e.get("name") == name)
        world.remove(element)
    for site in root.iter("site"):
        site.set("group", "4")
    for sensors in root.iter("sensor"):  # MuJoCo draws the rangefinders' rays (decorations: not drawn here)
        for rangefinder in sensors.findall("rangefinder"):
            sensors.remove(rangefinder)
    res = 201
    row, col = np.ogrid[-1:1:res * 1j, -1:1:res * 1j]
    bowl = 0.5 - np.cos(2 * np.pi * np.clip(np.sqrt(row ** 2 + col ** 2), 0.04, 1)) / 2
    bumps = np.random.default_rng(0).uniform(0.15, 1.0, (30, 30))
    at = np.linspace(0, 29, res)
    bumps = np.array([np.interp(at, np.arange(30), b) for b in bumps])  # along columns, then rows
    bumps = np.array([np.interp(at, np.arange(30), b) for b in bumps.T]).T
    root.find("asset/hfield").set("elevation", fmt((bowl * bumps).ravel()))
    eye, target = (2.2, -2.6, 1.6), (-0.5, 0.5, 0.3)
    world.insert(0, ET.fromstring(f'<camera name="world" pos="{fmt(eye)}" xyaxes="{fmt(xyaxes(eye, target))}" '
                                  'fovy="60"/>'))
    return ET.tostring(root, encoding="unicode")


def test_dm_control_quadruped_terrain_agrees_with_mujoco_renderer():
    """dm_control's quadruped on its escape terrain (80 k surface triangles, 30 m across, 5 m high; the floor
    plane cuts through its flat middle), a world camera over the robot towards the bowl's rim, 3 random states,
    64x48 (measured: depth agrees on 100% of pixels, segmentation on 99.99%: one pixel, where two of the robot's
    capsules meet (MuJoCo tessellates them); p99 depth error on the terrain 4.2e-6 m)."""
    close, same, seen, p99 = agreement(quadruped_xml(), ("world",))
    assert seen[0] > 0.2, f"the terrain is hardly in view: {seen}"
    assert close[0] >= 0.998, f"depth agrees on {close[0]:.2%} of pixels"
    assert same[0] >= 0.998, f"segmentation agrees on {same[0]:.2%} of pixels"
    assert p99 < 1e-3


# ------------------------------------------------------------------------------------------- paths and colours
def test_tiles_dense_rgb_and_the_systems_heights():
    """Tiles and dense give the same images; the field shades in its colour (a cell's face normal: the top
    straight below a camera looking down is lit fully); the heights drawn are the System's (what it collides)."""
    m, system, scene, state = scene_and_states(HFIELD_XML)
    assert scene.geom_type == ("hfield", "sphere") and scene.meshes.names == ("hfield:terrain",)
    tiled = render(scene, state, "oblique", H, W, rgb=True)
    dense = render(scene, state, "oblique", H, W, rgb=True, tile=0)
    for a, b in zip(tiled, dense):
        assert torch.equal(a, b)
    assert (tiled.segmentation == 0).any()
    flat = system.replace(hfield_height=torch.full_like(system.hfield_height, 0.2))
    level = Scene.build(m, flat)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    centre, zaxis = d.geom_xpos[0], d.geom_xmat[0].reshape(3, 3)[:, 2]
    cam = Camera.look_at(centre + 1.0 * zaxis, centre, up=tuple(d.geom_xmat[0].reshape(3, 3)[:, 1]), fovy=10)
    image = render(level, state, cam, 9, 9, rgb=True)
    assert image.segmentation[0, 4, 4] == 0
    assert abs(image.depth[0, 4, 4] - 0.8) < 1e-9  # 1 m above the field's origin, its level top 0.2 m up
    torch.testing.assert_close(image.rgb[0, 4, 4], torch.tensor([0.4, 0.6, 0.3], dtype=torch.float64), atol=1e-6,
                               rtol=0)  # MuJoCo's float32 rgba


def test_viewer_draws_the_field():
    """The viewer's triangles of an hfield geom are the scene's triangulation (in the geom's frame), and the
    browser viewer builds and records a scene with one."""
    m, _, scene, state = scene_and_states(HFIELD_XML, states=1)
    vertices, faces = scene_geom_mesh(scene, 0)
    expect_v, expect_f = hfield_mesh.triangulate(hfield_mesh.elevation(m, 0), m.hfield_size[0])
    np.testing.assert_allclose(vertices, expect_v, atol=1e-7)
    assert np.array_equal(faces, expect_f)
    pytest.importorskip("viser", reason="viser not installed (pip install viser)")
    from torchsim.render.viewer import Viewer

    viewer = Viewer(scene, host="127.0.0.1", port=8793, verbose=False)
    try:
        viewer.update(state)
        assert len(viewer.to_html(state, 0.05)) > 10_000
    finally:
        viewer.close()
