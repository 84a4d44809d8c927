"""Candidate contact pairs follow MuJoCo's filters: contype/conaffinity, <exclude>, <pair>, parent filter."""

import mujoco
import pytest

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
