"""Candidate contact pairs follow MuJoCo's filters: contype/conaffinity, <exclude>, <pair>, parent filter."""

import mujoco
import pytest
import torch

import torchsim
from models import ANT, CHAIN, HUMANOID, TWO_SPHERES


def _pairs(xml):
    return torchsim.load_mjcf(xml).num_contact_pairs


def _mujoco_contacts(xml):
    """MuJoCo's contact count at the model's initial pose (every pair in these scenes overlaps or touches)."""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    return d.ncon


def test_ant_feet_and_humanoid_feet_and_shins_only():
    assert torchsim.load_mjcf(str(ANT)).num_contact_pairs == 4
    assert torchsim.load_mjcf(str(HUMANOID)).num_contact_pairs == 4


def test_all_collide():
    assert _pairs(TWO_SPHERES.format(floor="", geom="", extra="")) == 3


def test_exclude():
    xml = TWO_SPHERES.format(floor="", geom="", extra='<contact><exclude body1="a" body2="b"/></contact>')
    assert _pairs(xml) == 2


def test_explicit_pair_only():
    xml = TWO_SPHERES.format(floor='contype="0" conaffinity="0"', geom='contype="0" conaffinity="0"',
                             extra='<contact><pair geom1="ga" geom2="floor"/></contact>')
    sys = torchsim.load_mjcf(xml)
    assert sys.num_contact_pairs == 1
    (group,) = sys.contact_groups
    assert group.kind == "sphere_plane"


@pytest.mark.parametrize("filterparent, expected", [("enable", 1), ("disable", 3)])
def test_parent_filter(filterparent, expected):
    """Overlapping spheres on parent, child (hinge) and grandchild (hinge): MuJoCo filters parent-child pairs
    only, so with the filter on just parent-grandchild remains; with it off all three pairs do."""
    xml = CHAIN.format(filterparent=filterparent)
    assert _pairs(xml) == expected
    assert _mujoco_contacts(xml) == expected  # the same as MuJoCo's own collision pipeline


def test_plane_contacts_skip_the_world_exactly():
    """With only plane pairs the contacts leave out the static world's side (``body_b`` None); every rigid-body
    response then equals the general pair form with the world's index, to the bit (its terms are zeros)."""
    from torchsim import lanes, rigid
    from torchsim.collision import contacts
    from torchsim.kinematics import with_world

    sys = torchsim.load_mjcf(str(ANT), dtype=torch.float64)
    q = torch.as_tensor(mujoco.MjModel.from_xml_path(str(ANT)).key_qpos[0])[None].repeat(3, 1)
    q[:, 2] -= 0.08  # feet into the floor
    torch.manual_seed(0)
    state = torchsim.init(sys, q, torch.randn(3, sys.nv, dtype=torch.float64))
    bodies = with_world(*(lanes.to_lanes(x, 1) for x in state[:4]))
    con = contacts(sys, bodies)
    assert con.body_b is None and bool((con.depth > 0).any())
    inv = rigid.inverse_inertia(sys, bodies.x_quat, rigid.body_inverse_inertia(sys))
    world = torch.full_like(con.body_a, sys.num_bodies)
    p_lin = torch.randn_like(con.pos)
    results = []
    for b in (None, world):
        r_a, r_b, v_rel = rigid.contact_arms(bodies, con.body_a, b, con.pos)
        w_n = rigid.pair_inverse_mass(inv, con.body_a, b, r_a, r_b, con.normal)
        scale_a, scale_b = rigid.active_count(con.body_a, b, (con.depth > 0).double(), sys.num_bodies + 1)
        moved = rigid.apply_pair_velocity(bodies, inv, con.body_a, b, r_a, r_b, p_lin, torch.zeros_like(p_lin),
                                          scale_a, scale_b)
        results.append((v_rel, w_n, scale_a, *moved))
    for skipped, general in zip(*results):
        assert torch.equal(skipped, general)


SLIDING_BOX = """<mujoco><option timestep="0.002"/><worldbody>
  <geom type="plane" size="2 2 .1" condim="{floor}"/>
  <body pos="0 0 0.1"><freejoint/><geom type="box" size=".1 .1 .1" mass="1" condim="{box}" friction="0.5"/></body>
</worldbody></mujoco>"""


@pytest.mark.parametrize("condim", [1, 3])
def test_condim_one_is_frictionless_like_mujoco(condim):
    """A box resting on the floor, sent sliding at 1 m/s: with condim 1 (MuJoCo's frictionless contact) it keeps its
    speed, with condim 3 friction (mu 1, the larger of the pair's) slows it to ~0.02 m/s (1 - mu g t). The pair's
    condim is the larger of the two geoms'. Speed after 0.1 s against MuJoCo's, within 0.05 m/s (the two cases
    differ by 0.98 m/s; torchsim's hard friction and MuJoCo's soft one by 0.016 m/s)."""
    xml = SLIDING_BOX.format(floor=1, box=condim)
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    d.qvel[0] = 1.0
    for _ in range(50):
        mujoco.mj_step(m, d)
    sys = torchsim.load_mjcf(xml, dtype=torch.float64)
    qd = torch.zeros(1, 6, dtype=torch.float64)
    qd[0, 0] = 1.0
    state = torchsim.init(sys, sys.q0[None], qd)
    for _ in range(50):
        state = torchsim.step(sys, state, torch.zeros(1, 0, dtype=torch.float64))
    print(f"condim {condim}: speed after 0.1 s {state.qd[0, 0].item():.4f} m/s (MuJoCo {d.qvel[0]:.4f})")
    assert abs(state.qd[0, 0].item() - d.qvel[0]) < 0.05
    assert (d.qvel[0] > 0.99) == (condim == 1)


def test_torsional_and_rolling_friction_warn_once_per_model():
    """Pairs with condim 4 or 6 keep their sliding friction, and the loader says once (not once per pair: a hand's
    fingertips on a floor make hundreds) how many pairs lose their torsional and rolling friction, naming some."""
    spheres = "".join(f'<body pos="{i} 0 1"><freejoint/><geom name="b{i}" type="sphere" size=".1"/></body>'
                      for i in range(5))
    xml = f'<mujoco><worldbody><geom name="floor" type="plane" size="9 9 .1" condim="6"/>{spheres}</worldbody></mujoco>'
    with pytest.warns(UserWarning) as caught:
        sys = torchsim.load_mjcf(xml)
    condim = [str(w.message) for w in caught if "condim" in str(w.message)]
    assert len(condim) == 1 and condim[0].startswith("5 geom pairs have condim 4 or 6, 'floor' and 'b0' (condim 6)")
    assert "and 2 more" in condim[0]
    assert all(torch.all(g.friction == 1.0) for g in sys.contact_groups)  # MuJoCo's default sliding friction, kept
