"""Wrong inputs and unsupported MJCF fail loudly, with messages that say what is wrong."""

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from models import F64, HUMANOID, PROJECTILE, TWO_HINGES


@pytest.fixture(scope="module")
def humanoid():
    sys = torchsim.load_mjcf(str(HUMANOID), dtype=F64)
    batch = 4
    state = torchsim.init(sys, sys.q0.expand(batch, -1).clone(), torch.zeros(batch, sys.nv, dtype=F64))
    return sys, state, batch


def test_wrong_ctrl_shape(humanoid):
    sys, state, batch = humanoid
    with pytest.raises(ValueError, match="ctrl") as err:
        torchsim.step(sys, state, torch.zeros(batch, sys.nu + 1, dtype=F64))
    assert f"({batch}, {sys.nu})" in str(err.value)  # the expected shape
    assert f"({batch}, {sys.nu + 1})" in str(err.value)  # and what was given
    with pytest.raises(ValueError, match="ctrl"):  # batch size must match the state
        torchsim.step(sys, state, torch.zeros(batch + 1, sys.nu, dtype=F64))


def test_wrong_ctrl_dtype(humanoid):
    sys, state, batch = humanoid
    with pytest.raises(ValueError) as err:
        torchsim.step(sys, state, torch.zeros(batch, sys.nu, dtype=torch.float32))
    assert "torch.float32" in str(err.value) and "torch.float64" in str(err.value)


def test_wrong_q_width(humanoid):
    sys, _, batch = humanoid
    with pytest.raises(ValueError, match=r"\bq\b") as err:
        torchsim.init(sys, torch.zeros(batch, sys.nq - 1, dtype=F64), torch.zeros(batch, sys.nv, dtype=F64))
    assert str(sys.nq) in str(err.value)
    with pytest.raises(ValueError, match="qd"):
        torchsim.init(sys, sys.q0.expand(batch, -1).clone(), torch.zeros(batch, sys.nv + 2, dtype=F64))


def test_missing_file(tmp_path):
    path = tmp_path / "no_such_model.xml"
    with pytest.raises(FileNotFoundError) as err:
        torchsim.load_mjcf(str(path))
    assert str(path) in str(err.value)


def test_spatial_tendon_unsupported():
    xml = TWO_HINGES.format(extra="""<worldbody><site name="a" pos="0 0 2"/><site name="b" pos="0 0 3"/></worldbody>
        <tendon><spatial name="cable"><site site="a"/><site site="b"/></spatial></tendon>""")
    mujoco.MjModel.from_xml_string(xml)  # valid MJCF: the rejection is torchsim's
    with pytest.raises(torchsim.UnsupportedMJCFError, match="'cable'.*spatial"):
        torchsim.load_mjcf(xml)


def test_equality_unsupported():
    xml = TWO_HINGES.format(extra='<equality><connect name="pin" body1="l2" anchor="0.3 0 0"/></equality>')
    mujoco.MjModel.from_xml_string(xml)  # <tendon> and <joint> equality constraints load: tests/test_equality.py
    with pytest.raises(torchsim.UnsupportedMJCFError, match="equality constraint 'pin'.*<connect>"):
        torchsim.load_mjcf(xml)


CYLINDER = """
<mujoco>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.1"/>
    <body pos="0 0 1"><freejoint/>
      <geom name="barrel" type="cylinder" size="0.1 0.2" {flags}/>
      <geom type="sphere" size="0.05"/>
    </body>
  </worldbody>
</mujoco>
"""


MESH = """
<mujoco>
  <asset><mesh name="tetrahedron" vertex="0 0 0  0.1 0 0  0 0.1 0  0 0 0.1"/></asset>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.1"/>
    <body pos="0 0 1"><freejoint/>
      <geom name="rock" type="mesh" mesh="tetrahedron"/>
    </body>
  </worldbody>
</mujoco>
"""


def test_colliding_mesh_unsupported():
    mujoco.MjModel.from_xml_string(MESH)
    with pytest.raises(torchsim.UnsupportedMJCFError) as err:
        torchsim.load_mjcf(MESH)
    msg = str(err.value)
    assert "rock" in msg and "MESH" in msg
    for shape in ("plane", "sphere", "capsule", "box", "ellipsoid", "cylinder"):
        assert shape in msg


def test_visual_cylinder_loads():
    xml = CYLINDER.format(flags='contype="0" conaffinity="0"')
    sys = torchsim.load_mjcf(xml, dtype=F64)
    m = mujoco.MjModel.from_xml_string(xml)
    # the visual cylinder still contributes its mass; only the sphere touches the floor
    assert np.isclose(sys.body_mass[0].item(), m.body_mass[1], rtol=1e-12)
    assert sys.num_contact_pairs == 1
    state = torchsim.init(sys, sys.q0[None].clone(), torch.zeros(1, sys.nv, dtype=F64))
    state = torchsim.step(sys, state, torch.zeros(1, 0, dtype=F64))
    assert not state.diverged.any()


def test_unknown_method():
    with pytest.raises(ValueError) as err:
        torchsim.load_mjcf(PROJECTILE, method="rk4")
    msg = str(err.value)
    assert "rk4" in msg and "xpbd" in msg and "spring" in msg
