"""Cylinder and ellipsoid contacts against MuJoCo: rest poses on a plane, and contact distances on sampled poses.

MuJoCo's soft contacts rest slightly inside the floor (0.14 mm for the cylinder on its cap, 0.21 mm on its side,
about 1 mm for the ellipsoid below); torchsim's spring method rests up to 0.75 mm deep (its Baumgarte
equilibrium), XPBD on the surface. So rest heights are checked within 1 mm of the exact geometric height, which
a wrong support point (a capsule's rounded end, a cylinder's centre instead of its rim, the wrong semi-axis) misses
by centimetres.
"""

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from models import F64, METHODS, axis_z, rest_pose
from torchsim import collision_round, lanes
from torchsim.collision import contacts
from torchsim.kinematics import with_world

REST_TOL = 1e-3

DROP = """
<mujoco>
  <option timestep="0.002"/>
  <worldbody>
    <geom type="plane" size="2 2 0.1"/>
    <body pos="0 0 {z}" euler="{euler}"><freejoint/><geom {geom}/></body>
  </worldbody>
</mujoco>
"""



@pytest.mark.parametrize("method", METHODS)
def test_cylinder_rests_on_cap(method):
    """Radius 0.1, half-height 0.05, dropped 2 mm with a small tilt: it settles flat on its cap at z = 0.05."""
    mj, ts = rest_pose(DROP.format(z=0.052, euler="3 4 0", geom='type="cylinder" size="0.1 0.05"'), method, 0.2)
    assert abs(mj[2] - 0.05) < REST_TOL and abs(axis_z(mj[3:7])) > 1 - 1e-6
    assert abs(ts[2] - 0.05) < REST_TOL
    assert abs(axis_z(ts[3:7])) > 1 - 1e-6  # flat on the cap, like MuJoCo's


@pytest.mark.parametrize("method", METHODS)
def test_cylinder_rests_on_side(method):
    """Radius 0.1, half-height 0.3, lying on its side: it stays there at z = radius, axis level."""
    mj, ts = rest_pose(DROP.format(z=0.102, euler="90 3 0", geom='type="cylinder" size="0.1 0.3"'), method, 0.2)
    assert abs(mj[2] - 0.1) < REST_TOL and abs(axis_z(mj[3:7])) < 1e-6
    assert abs(ts[2] - 0.1) < REST_TOL
    assert abs(axis_z(ts[3:7])) < 1e-4
    assert np.allclose(ts[3:7], mj[3:7], atol=1e-3)  # no roll or yaw either


@pytest.mark.parametrize("method", METHODS)
def test_ellipsoid_rests_on_its_semi_axis(method):
    """Semi-axes 0.1, 0.2, 0.05, dropped flat (turned about z): it rests at z = 0.05, its shortest semi-axis."""
    mj, ts = rest_pose(DROP.format(z=0.052, euler="0 0 30", geom='type="ellipsoid" size="0.1 0.2 0.05"'), method, 0.2)
    assert abs(mj[2] - 0.05) < 1.5e-3  # MuJoCo's rest penetration is 1.1 mm here
    assert abs(ts[2] - 0.05) < REST_TOL


PAIR = """
<mujoco>
  <option gravity="0 0 0"/>
  <worldbody>
    {floor}
    <body name="a"><freejoint/><geom {geom_a}/></body>
    <body name="b" pos="0 0 1"><freejoint/><geom {geom_b}/></body>
  </worldbody>
</mujoco>
"""
SHAPES = {
    "sphere": 'type="sphere" size="0.05"',
    "capsule": 'type="capsule" size="0.03 0.08"',
    "hand": 'type="ellipsoid" size="0.048 0.02 0.06"',  # humanoid_CMU's hands
    "flat": 'type="ellipsoid" size="0.1 0.02 0.05"',
    "thin": 'type="ellipsoid" size="0.03 0.08 0.01"',
    "cylinder": 'type="cylinder" size="0.05 0.05"',
    "disc": 'type="cylinder" size="0.08 0.01"',
    "rod": 'type="cylinder" size="0.02 0.1"',
    "plane": None,
}
# (shape a, shape b, kind, bound on |ours - MuJoCo| [m]). Exact pairs: float64 round-off. Capsule pairs: the
# bisection's bound is the segment's length times 2^-11 (78 um here); measured up to 5e-7. Ellipsoid pairs: MuJoCo's
# own convex solver stops at ccd_tolerance (1e-6); measured 9.6e-7 for the hands, up to 8.9e-6 for semi-axis
# ratios of 8 (over a few seeds; 9.5e-7 with this one). Cylinder-cylinder: the climbed separating normal's
# separation, never too shallow; measured up to 9.2e-5 too deep (1.6e-5 apart) over 5 seeds and 8 pairs of sizes.
CASES = [
    ("sphere", "hand", "sphere_ellipsoid", 1e-9),
    ("sphere", "cylinder", "sphere_cylinder", 1e-9),
    ("capsule", "hand", "capsule_ellipsoid", 2e-6),
    ("capsule", "disc", "capsule_cylinder", 2e-6),
    ("hand", "hand", "ellipsoid_ellipsoid", 2e-6),
    ("flat", "thin", "ellipsoid_ellipsoid", 1e-5),
    ("hand", "plane", "ellipsoid_plane", 1e-9),
    ("cylinder", "plane", "cylinder_plane", 1e-9),
    ("disc", "plane", "cylinder_plane", 1e-9),
    ("cylinder", "disc", "cylinder_cylinder", 1e-4),
    ("rod", "cylinder", "cylinder_cylinder", 1e-4),
    ("disc", "disc", "cylinder_cylinder", 1e-4),
]


def _sampled_distances(shape_a, shape_b, count=200, band=(-0.01, 0.02), seed=0):
    """MuJoCo's ``mj_geomDistance`` and torchsim's (the smallest over the pair's points) on random poses whose
    MuJoCo distance lies in ``band`` [m], and the pair's kind."""
    plane = shape_b == "plane"
    xml = PAIR.format(floor='<geom type="plane" size="1 1 0.1"/>' if plane else "", geom_a=SHAPES[shape_a],
                      geom_b=SHAPES["sphere"] if plane else SHAPES[shape_b])
    if plane:  # the second body never touches the floor: no contact with it, nothing to sample
        xml = xml.replace('<geom type="sphere" size="0.05"/>', '<geom type="sphere" size="0.05" contype="0" '
                                                               'conaffinity="0"/>')
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    g_a, g_b = (1, 0) if plane else (0, 1)
    rng = np.random.default_rng(seed)
    reach = m.geom_rbound[g_a] + (0.0 if plane else m.geom_rbound[g_b])
    poses, mj_dist = [], []
    while len(poses) < count:
        q = d.qpos.copy()
        for body in range(2):  # random orientations; body b placed at random around a
            quat = rng.normal(size=4)
            q[7 * body + 3:7 * body + 7] = quat / np.linalg.norm(quat)
        q[:3] = (0, 0, rng.uniform(-reach, reach)) if plane else (0, 0, 0)
        q[7:10] = (0, 0, 1) if plane else rng.uniform(-reach, reach, 3)
        d.qpos[:] = q
        mujoco.mj_kinematics(m, d)
        dist = mujoco.mj_geomDistance(m, d, g_a, g_b, 1.0, None)
        if band[0] < dist < band[1]:
            poses.append(q)
            mj_dist.append(dist)
    sys = torchsim.load_mjcf(xml, dtype=F64)
    (group,) = sys.contact_groups
    state = torchsim.init(sys, torch.as_tensor(np.array(poses)), torch.zeros(count, sys.nv, dtype=F64))
    con = contacts(sys, with_world(*(lanes.to_lanes(x, 1) for x in state[:4])))
    return np.array(mj_dist), (-con.depth).amin(0).numpy(), group.kind


@pytest.mark.parametrize("shape_a, shape_b, kind, bound", CASES)
def test_contact_distance_matches_mujoco(shape_a, shape_b, kind, bound):
    mj, ours, loaded_kind = _sampled_distances(shape_a, shape_b)
    assert loaded_kind == kind
    assert np.abs(ours - mj).max() < bound


def test_capsule_bisection_matters():
    """The capsule's bisected middle sphere is what finds a capsule lying across a disc off its centre: with it
    at the segment's midpoint instead (no bisection), the distance errs by millimetres."""
    mj, ours, _ = _sampled_distances("capsule", "disc", count=100)
    assert np.abs(ours - mj).max() < 2e-6
    iterations = collision_round.SEGMENT_ITERATIONS
    try:
        collision_round.SEGMENT_ITERATIONS = 0
        _, crude, _ = _sampled_distances("capsule", "disc", count=100)
    finally:
        collision_round.SEGMENT_ITERATIONS = iterations
    assert np.abs(crude - mj).max() > 1e-3


def test_cylinder_pair_errs_deep_and_needs_its_climb():
    """Cylinder-cylinder distances are never shallower than MuJoCo's (a lower bound: contacts err deep, never
    missed); without the separating normal's climb (its best candidate as is) they err by millimetres."""
    mj, ours, _ = _sampled_distances("cylinder", "disc", count=200, seed=1)
    assert (ours - mj).max() < 1e-9 and (ours - mj).min() > -1e-4
    iterations = collision_round.NORMAL_ITERATIONS
    try:
        collision_round.NORMAL_ITERATIONS = 0
        _, crude, _ = _sampled_distances("cylinder", "disc", count=200, seed=1)
    finally:
        collision_round.NORMAL_ITERATIONS = iterations
    assert (crude - mj).max() < 1e-9 and (crude - mj).min() < -1e-3


STACK = """
<mujoco>
  <option timestep="0.004" gravity="0 {gy} -9.81"/>
  <worldbody>
    <geom type="plane" size="2 2 0.1"/>
    {bodies}
  </worldbody>
</mujoco>
"""


@pytest.mark.parametrize("method", METHODS)
def test_cylinders_stacked_cap_on_cap(method):
    """A cylinder (radius 0.04, half-height 0.03) set down, slightly tilted, on another's cap (0.06, 0.05): it
    settles flat at z = 0.13, 0.08 above the bottom one, as in MuJoCo. The gap between them is
    the pair's own; spring's bottom cylinder sinks 1.3 mm deeper into the floor than MuJoCo's (its impulses are
    averaged over a body's active contacts: a box stack sinks 2.2 mm)."""
    xml = STACK.format(gy=0, bodies="""
    <body pos="0 0 0.0501"><freejoint/><geom type="cylinder" size="0.06 0.05"/></body>
    <body pos="0.005 0 0.1305" euler="0.5 -0.5 0"><freejoint/><geom type="cylinder" size="0.04 0.03"/></body>""")
    mj, ts = rest_pose(xml, method, seconds=0.1)
    assert abs(mj[9] - mj[2] - 0.08) < REST_TOL and abs(mj[9] - 0.13) < REST_TOL
    assert abs((ts[9] - ts[2]) - (mj[9] - mj[2])) < REST_TOL
    assert abs(ts[9] - mj[9]) < (REST_TOL if method == "xpbd" else 2.5e-3)  # spring: 1.8 mm
    assert abs(axis_z(ts[10:14])) > 1 - 1e-4 and abs(ts[7] - 0.005) < 2e-3  # flat, not slid off


@pytest.mark.parametrize("method", METHODS)
def test_cylinders_side_by_side(method):
    """A cylinder (radius 0.04) lying on the floor, pushed sideways (gravity's y component) against a fixed one
    (radius 0.05) lying parallel: it rests with the axes 0.09 apart, side on side, as in MuJoCo."""
    xml = STACK.format(gy=-4, bodies="""
    <geom type="cylinder" size="0.05 0.3" pos="0 0 0.05" euler="0 90 0"/>
    <body pos="0.01 0.092 0.041" euler="0 90 0"><freejoint/><geom type="cylinder" size="0.04 0.15"/></body>""")
    mj, ts = rest_pose(xml, method, seconds=0.1)
    assert abs(mj[1] - 0.09) < 2e-3 and abs(mj[2] - 0.04) < REST_TOL  # MuJoCo: 1.5 mm deep side on side
    assert abs(ts[1] - 0.09) < REST_TOL and abs(ts[1] - mj[1]) < 2e-3  # ours: 0.6 (xpbd), 0.9 mm (spring)
    assert abs(ts[2] - mj[2]) < (REST_TOL if method == "xpbd" else 2 * REST_TOL)  # spring: 1 mm deep in the floor
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, ts[3:7])
    assert abs(mat[2]) > 1 - 1e-4  # its axis still along x
