"""Height fields (``<hfield>``, ``torchsim.collision_hfield``) against MuJoCo: the surface, the contacts of each
primitive, a drop, and dm_control's quadruped loading.

MuJoCo collides a geom with each triangle's prism by its convex solver. Where the geom's deepest point lies inside
one triangle, that contact is the geom's support point against the triangle's plane, which torchsim computes in
closed form: spheres and capsules match MuJoCo's to 1e-10 m and 1e-9 in the normal (measured ~1e-11 and 4e-10,
float64), ellipsoids and cylinders (MuJoCo's normal is the geom's own at its solver's contact point) to 1e-7 m and
1e-5 (measured 1e-8 and 3e-6). A sphere over a cell edge or vertex touches several prisms: each of MuJoCo's
contacts is one of torchsim's (the same closest-point distances). Boxes: MuJoCo's solver is exact on level cells
(5 mm exactly, as torchsim's corners), but on a slope it is not: a box 5 mm into a 0.3 m-per-2 m slope reads
1.49 mm in MuJoCo 4.0 unrotated (exact when rotated), so a box on a slope is checked against the exact depth of its
deepest corner below the triangle's plane (from MuJoCo's own ray cast of the surface), not against MuJoCo's number
(which reads 5 mm where that corner is 7.2 to 11.7 mm deep, measured at the 5 triangles tested).
"""

import glob
import os

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from torchsim import collision, collision_hfield, kinematics, lanes, pipeline
from torchsim.execution.kernel import rows
from torchsim.execution.kernel.step import StepKernel

F64 = torch.float64
NROW, NCOL = 7, 9
ELEVATION = np.random.default_rng(0).uniform(0, 1, (NROW, NCOL))
ELEVATION[1:3, 6:9] = 0.5  # a level plateau: cells (4, 6) and (4, 7) (MuJoCo reads the rows from +y down)
FIELD = (f'<hfield name="h" nrow="{NROW}" ncol="{NCOL}" size="1.0 0.8 0.3 0.1" '
         f'elevation="{" ".join(f"{v:.4f}" for v in ELEVATION.ravel())}"/>')
SCENE = """<mujoco><asset>{field}</asset><worldbody>
<geom name="terrain" type="hfield" hfield="h" pos="0.1 -0.05 0.02" euler="{euler}"/>
<body name="b" pos="0 0 1"><freejoint/><geom name="g" type="{shape}" size="{size}"/></body></worldbody></mujoco>"""
TILTED = "0.1 -0.15 0.3"  # the field's frame turned, so that the world and field frames differ
QUAT = np.array([0.9, 0.3, -0.2, 0.25]) / np.linalg.norm([0.9, 0.3, -0.2, 0.25])
SINK = 0.005  # [m] MuJoCo's deepest contact, set by bisection on the height


def _model(shape, size, euler=TILTED):
    xml = SCENE.format(field=FIELD, euler=euler, shape=shape, size=size)
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    return xml, m, d


def _surface(m, d, x, y) -> float:
    """The field's height under ``(x, y)`` by MuJoCo's ray cast (the moving body excluded)."""
    return 5.0 - mujoco.mj_ray(m, d, np.array([x, y, 5.0]), np.array([0, 0, -1.0]), None, 1, 1, np.zeros(1, np.int32))


def _centroid(m, d, row, col, tri):
    """World xy of the centroid of triangle ``tri`` of cell ``(row, col)`` (0: the one over the diagonal)."""
    sx, sy = m.hfield_size[0, :2]
    u, v = col + (1 / 3 if tri == 0 else 2 / 3), row + (2 / 3 if tri == 0 else 1 / 3)
    local = np.array([u * 2 * sx / (NCOL - 1) - sx, v * 2 * sy / (NROW - 1) - sy, 0.0])
    return (d.geom_xpos[0] + d.geom_xmat[0].reshape(3, 3) @ local)[:2]


def _place(m, d, xy, quat, sink=SINK):
    """The geom at ``xy`` turned by ``quat``, lowered until MuJoCo's deepest contact is ``sink`` deep."""
    d.qpos[:2], d.qpos[3:7] = xy, quat
    surface = _surface(m, d, *xy)
    lo, hi = surface - 0.02, surface + 0.3

    def depth(z):
        d.qpos[2] = z
        mujoco.mj_forward(m, d)
        return max([-c.dist for c in d.contact[:d.ncon]], default=-1.0)

    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if depth(mid) > sink else (lo, mid)
    depth(lo)


def _contacts(xml, qpos):
    """torchsim's contacts at ``qpos``: depth ``(C,)``, normal ``(C, 3)``, point ``(C, 3)``."""
    sys = torchsim.load_mjcf(xml, dtype=F64)
    state = pipeline.init(sys, torch.tensor(qpos)[None], torch.zeros(1, sys.nv, dtype=F64))
    c = collision.contacts(sys, kinematics.with_world(*(lanes.to_lanes(x, 1) for x in state[:4])))
    return c.depth[:, 0].numpy(), c.normal[..., 0].T.numpy(), c.pos[..., 0].T.numpy()


def _deepest_agree(shape, size, xy, quat):
    xml, m, d = _model(shape, size)
    _place(m, d, xy(m, d) if callable(xy) else xy, quat)
    depth, normal, pos = _contacts(xml, d.qpos)
    i, j = depth.argmax(), min(range(d.ncon), key=lambda k: d.contact[k].dist)
    return abs(depth[i] + d.contact[j].dist), np.abs(normal[i] - d.contact[j].frame[:3]).max(), depth, d


def test_surface_is_mujocos():
    """Points 0.1 mm above and below MuJoCo's ray-cast surface, at 200 random places of the turned field: torchsim's
    signed distance from its triangles has the right sign at each (grid mapping, diagonal, elevation scale)."""
    xml, m, d = _model("sphere", "0.05")
    sys = torchsim.load_mjcf(xml, dtype=F64)
    rng = np.random.default_rng(1)
    xy = d.geom_xpos[0, :2] + rng.uniform(-0.6, 0.6, (200, 2))
    z = np.array([_surface(m, d, x, y) for x, y in xy])
    for offset, sign in ((1e-4, 1), (-1e-4, -1)):
        pa = torch.tensor(np.column_stack([xy, z + offset])).T.unsqueeze(1)  # (3, 1, B)
        geom = torch.tensor([0])
        pb = lanes.param(sys.geom_pos, 1, 1).index_select(-2, geom)
        rot_b = torchsim.spatial.quat_to_mat(lanes.param(sys.geom_quat, 1, 1)).index_select(-2, geom)
        rot_a = torch.eye(3, dtype=F64).view(3, 3, 1, 1).expand(3, 3, 1, 200)
        _, _, dist = collision_hfield.pair_contacts(
            sys, "sphere_hfield", geom, torch.zeros(1, 1, dtype=F64), pa, rot_a, torch.zeros(3, 1, 1, dtype=F64),
            pb, rot_b, collision._box_corners, collision._point_box)
        nearest = dist.amin(-2)[0]
        assert (torch.sign(nearest) == sign).all()
        assert nearest.abs().max() < 1.0001e-4  # at most the vertical offset


@pytest.mark.parametrize("xy", [(0.0, 0.0), (0.3, 0.2), (-0.4, -0.3), (0.35, -0.25), (-0.5, 0.4)])
def test_sphere_contacts_match_mujoco(xy):
    """A sphere 5 mm into the field, inside a triangle or across cell edges and vertices (up to 6 of MuJoCo's
    contacts): every MuJoCo contact is one of torchsim's (distance 1e-9 m, normal 1e-7, point 1e-7 m) and every
    active torchsim contact one of MuJoCo's (torchsim keeps the 4 deepest, so at most 4)."""
    xml, m, d = _model("sphere", "0.05")
    _place(m, d, xy, (1, 0, 0, 0))
    depth, normal, pos = _contacts(xml, d.qpos)
    mj = [(-c.dist, c.frame[:3].copy(), c.pos.copy()) for c in d.contact[:d.ncon]]
    active = depth > 0
    assert 1 <= active.sum() <= 4
    for dep, n, p in zip(depth[active], normal[active], pos[active]):  # each of ours is one of MuJoCo's
        assert min(abs(dep - md) + np.abs(n - mn).max() + np.abs(p - mp).max() for md, mn, mp in mj) < 1e-7
    for md, mn, mp in sorted(mj, key=lambda c: -c[0])[:4]:  # MuJoCo's deepest 4 are ours (ties: duplicates)
        assert min(abs(dep - md) + np.abs(n - mn).max() for dep, n in zip(depth, normal)) < 1e-7


CELLS = [(1, 2, 0), (1, 2, 1), (3, 5, 0), (4, 1, 1), (2, 6, 1)]


@pytest.mark.parametrize("cell", CELLS)
@pytest.mark.parametrize("shape, size, depth_tol, normal_tol", [
    ("sphere", "0.05", 1e-10, 1e-9), ("capsule", "0.04 0.06", 1e-10, 1e-9),
    ("ellipsoid", "0.05 0.07 0.04", 1e-6, 1e-5), ("cylinder", "0.04 0.05", 1e-6, 1e-5)])
def test_deepest_contact_inside_a_triangle_matches_mujoco(shape, size, depth_tol, normal_tol, cell):
    """Each primitive (turned, on the turned field's slopes) 5 mm into the triangle under it: the deepest contact's
    depth and normal are MuJoCo's (tolerances: the module docstring)."""
    quat = (1, 0, 0, 0) if shape == "sphere" else QUAT
    ddepth, dnormal, depth, _ = _deepest_agree(shape, size, lambda m, d: _centroid(m, d, *cell), quat)
    print(f"{shape} {cell}: depth {depth.max():.6f} m, |d depth| {ddepth:.1e} m, |d normal| {dnormal:.1e}")
    assert ddepth < depth_tol and dnormal < normal_tol


@pytest.mark.parametrize("quat", [(1, 0, 0, 0), (np.cos(0.26), 0, 0, np.sin(0.26))])
def test_box_on_a_level_cell_matches_mujoco(quat):
    """A box 5 mm into the level plateau (cells (4, 6), (4, 7), field not turned), flat on its face (turned about
    z only): MuJoCo's solver is exact there, and so are torchsim's corners. (Tilted so that a corner goes in first,
    MuJoCo's reads 5 mm where the corner is 8.1 mm deep: its solver is not exact for box-prism pairs.)"""
    xml, m, d = _model("box", "0.03 0.04 0.02", euler="0 0 0")
    _place(m, d, _centroid(m, d, 4, 6, 1) + np.array([0.05, 0.0]), quat)
    depth, normal, _ = _contacts(xml, d.qpos)
    i = depth.argmax()
    assert abs(depth[i] - SINK) < 1e-9 and np.abs(normal[i] - [0, 0, 1]).max() < 1e-9
    assert all(abs(-c.dist - SINK) < 1e-9 and np.abs(c.frame[:3] - [0, 0, 1]).max() < 1e-9
               for c in d.contact[:d.ncon] if -c.dist > SINK - 1e-9)


@pytest.mark.parametrize("cell", CELLS)
def test_box_on_a_slope_is_its_deepest_corner(cell):
    """A turned box on the turned field's slopes: its deepest contact is its deepest corner's depth below the
    triangle's plane along the plane's normal, the plane taken from MuJoCo's ray cast of the surface around the
    corner (MuJoCo's own contact is not exact there: the module docstring)."""
    xml, m, d = _model("box", "0.03 0.04 0.02")
    _place(m, d, _centroid(m, d, *cell), QUAT)
    depth, normal, _ = _contacts(xml, d.qpos)
    rot, size = d.geom_xmat[1].reshape(3, 3), m.geom_size[1]
    corners = d.geom_xpos[1] + np.array([rot @ (size * np.array([a, b, c]))
                                         for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)])
    below = np.array([_surface(m, d, *p[:2]) - p[2] for p in corners])
    corner = corners[below.argmax()]
    e = 1e-3  # the surface's plane from three ray casts within 1 mm of the corner (inside its triangle)
    pts = [np.array([corner[0] + dx, corner[1] + dy, _surface(m, d, corner[0] + dx, corner[1] + dy)])
           for dx, dy in ((0, 0), (e, 0), (0, e))]
    n = np.cross(pts[1] - pts[0], pts[2] - pts[0])
    n /= np.linalg.norm(n)
    exact = np.dot(pts[0] - corner, n)
    i = depth.argmax()
    print(f"box {cell}: depth {depth[i]:.6f} m, exact {exact:.6f} m, MuJoCo {-d.contact[0].dist:.6f} m")
    assert abs(depth[i] - exact) < 1e-9 and np.abs(normal[i] - n).max() < 1e-6


DROP = """<mujoco><option timestep="0.0005"/><asset>
<hfield name="h" nrow="5" ncol="9" size="1.0 0.6 0.3 0.1" elevation="{elevation}"/></asset><worldbody>
<geom name="terrain" type="hfield" hfield="h" condim="{condim}"/>
<body name="b" pos="0.15 0.08 0.3"><freejoint/><geom name="g" type="sphere" size="0.1" condim="{condim}"/></body>
</worldbody></mujoco>"""


@pytest.mark.parametrize("condim, model, tol", [(1, "soft", 1e-9), (3, "soft", 1e-3), (3, "impulse", 1.5e-2)])
def test_sphere_drop_on_a_slope_follows_mujoco(condim, model, tol):
    """A sphere dropped onto the slope (8.5 degrees, one triangle under it) and sliding or rolling down for 0.2 s,
    at MuJoCo's timestep = torchsim's substep: frictionless on soft contacts, the same trajectory as MuJoCo's
    (measured 1e-11 m: the same contact, the same arithmetic); with friction, soft within 1 mm (measured 0.47 mm:
    friction is a Coulomb impulse, not MuJoCo's cone); the impulse contact within 1.5 cm (measured 8.6 mm at the
    landing, which it stops within a substep where MuJoCo's spring-damper sinks it)."""
    x = np.linspace(0, 1, 9)
    elevation = np.tile(x, (5, 1)) * (1 + 0.3 * np.sin(np.arange(5)))[:, None]
    xml = DROP.format(elevation=" ".join(f"{v:.4f}" for v in (elevation / elevation.max()).ravel()), condim=condim)
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    sys = torchsim.load_mjcf(xml, dtype=F64, contact_model=model)
    state = torchsim.init(sys, sys.q0[None].clone(), torch.zeros(1, sys.nv, dtype=F64))
    ctrl = torch.zeros(1, 0, dtype=F64)
    err, landed = 0.0, False
    for _ in range(400):
        mujoco.mj_step(m, d)
        state = torchsim.step(sys, state, ctrl)
        err = max(err, np.abs(state.q[0, :3].numpy() - d.qpos[:3]).max())
        landed |= d.ncon > 0
    print(f"condim {condim} {model}: max |error| {err:.2e} m; final x {d.qpos[0]:.4f} m (from 0.15)")
    assert landed and d.qpos[0] < 0.14  # it landed and moved down the slope
    assert err < tol


def test_hfield_on_a_moving_body_is_refused():
    xml = f"""<mujoco><asset>{FIELD}</asset><worldbody><geom type="plane" size="5 5 0.1"/>
    <body pos="0 0 1"><freejoint/><geom name="moving" type="hfield" hfield="h"/></body></worldbody></mujoco>"""
    with pytest.raises(torchsim.UnsupportedMJCFError, match="'moving'"):
        torchsim.load_mjcf(xml)


def test_mesh_against_hfield_is_refused():
    xml = f"""<mujoco><asset>{FIELD}<mesh name="tet" vertex="0 0 0 0.1 0 0 0 0.1 0 0 0 0.1"/></asset><worldbody>
    <geom type="hfield" hfield="h"/><body pos="0 0 1"><freejoint/><geom name="g" type="mesh" mesh="tet"/></body>
    </worldbody></mujoco>"""
    with pytest.raises(torchsim.UnsupportedMJCFError, match="mesh-hfield contacts are not implemented"):
        torchsim.load_mjcf(xml)


def test_step_kernel_refuses_height_fields():
    """Gathering the window's cells by index is outside the row graphs' contract: the kernel refuses by name
    (``Stepper`` then runs ``loop``)."""
    sys = torchsim.load_mjcf(SCENE.format(field=FIELD, euler=TILTED, shape="sphere", size="0.1"))
    with pytest.raises(rows.Unsupported, match="height fields"):
        StepKernel(sys)


def _quadruped():
    import importlib.util

    spec = importlib.util.find_spec("dm_control")
    roots = [os.path.dirname(spec.origin)] if spec else []
    roots += sorted(glob.glob(os.path.expanduser("~/.cache/torchsim/third_party/dm_control-*/dm_control")))
    for root in roots:
        path = os.path.join(root, "suite", "quadruped.xml")
        if os.path.isfile(path):
            return path
    pytest.skip("dm_control's quadruped.xml is not installed (nor cached by studies/check_third_party.py)")


def test_dm_control_quadruped_loads_and_steps():
    """dm_control's quadruped: its 201 x 201 terrain (zeros in the XML; the escape task writes it at run time) loads,
    its toes, legs, torso and eyes collide with it (windows of 2 to 4 cells of 0.3 m), and it steps. A level terrain
    set 4 cm above its floor (``sys.replace(hfield_height=...)``) carries it as MuJoCo's does: torso height after
    0.2 s 0.4858 m (MuJoCo 0.4914; 0.4390 and 0.4415 on the floor alone: the same 2.5 mm gap)."""
    sys = torchsim.load_mjcf(_quadruped(), dtype=F64)
    kinds = {k: (wy, wx) for k, wy, wx in sys.hfield_windows}
    assert set(kinds) == {"sphere_hfield", "capsule_hfield", "ellipsoid_hfield", "cylinder_hfield"}
    assert all(2 <= w <= 4 for window in kinds.values() for w in window)
    m = mujoco.MjModel.from_xml_path(_quadruped())
    d = mujoco.MjData(m)
    level = np.full(201 * 201, (0.04 + 0.01) / m.hfield_size[0, 2])  # the field's geom sits 1 cm below the floor
    m.hfield_data[:] = level
    sys = sys.replace(hfield_height=torch.as_tensor(level * m.hfield_size[0, 2]))
    state = torchsim.init(sys, sys.q0[None].clone(), torch.zeros(1, sys.nv, dtype=F64))
    ctrl = torch.zeros(1, sys.nu, dtype=F64)
    for _ in range(40):
        mujoco.mj_step(m, d)
        state = torchsim.step(sys, state, ctrl)
    print(f"torso height after 0.2 s: {state.q[0, 2]:.4f} m (MuJoCo {d.qpos[2]:.4f})")
    assert not state.diverged.any()
    assert abs(state.q[0, 2].item() - d.qpos[2]) < 0.015 and state.q[0, 2] > 0.47  # 0.44 on the floor
