"""MuJoCo's touch sensor from ``torchsim.contact_forces``: bodies at rest on a plane, sites covering all, some or none
of their contacts, against MuJoCo's ``sensordata`` (both settled first; the sensors read the weight a zone holds)."""

import mujoco
import pytest
import torch

import torchsim
from models import F64

XML = """
<mujoco><option timestep="0.002"/><worldbody><geom type="plane" size="5 5 .1"/>
  <body name="box" pos="0 0 0.3"><freejoint/><geom type="box" size="0.2 0.1 0.05" mass="2"/>
    <site name="bottom" type="box" pos="0 0 -0.05" size="0.21 0.11 0.01"/>
    <site name="left_corners" type="sphere" pos="-0.2 0 -0.05" size="0.12"/>
    <site name="one_corner" type="ellipsoid" pos="0.2 0.1 -0.05" size="0.03 0.03 0.02"/>
    <site name="top" type="box" pos="0 0 0.05" size="0.21 0.11 0.01"/>
    <site name="above" type="cylinder" pos="0 0 0.2" size="0.3 0.05"/></body>
  <body name="ball" pos="1 0 0.3"><freejoint/><geom type="sphere" size="0.1" mass="1"/>
    <site name="ball_zone" type="capsule" size="0.12 0.05"/></body>
</worldbody>
<sensor><touch site="bottom"/><touch site="left_corners"/><touch site="one_corner"/><touch site="top"/>
  <touch site="above"/><touch site="ball_zone"/></sensor></mujoco>"""


@pytest.mark.parametrize("contact_model", ["impulse", "soft"])
def test_touch_reads_mujocos_weights(contact_model):
    """The whole box (19.62 N), two of its four corners (9.81 N), one (4.905 N), none (its top; a zone above it
    that only the ray test could reach, and the ray points away from the box), the ball in a capsule zone (9.81 N):
    MuJoCo's values within 0.5 % of the weight (a substep's impulse over its length, the bodies settling by ~1e-4
    m/s); zero where MuJoCo reads zero."""
    m = mujoco.MjModel.from_xml_string(XML)
    d = mujoco.MjData(m)
    for _ in range(500):
        mujoco.mj_step(m, d)
    mujoco.mj_forward(m, d)
    sys = torchsim.load_mjcf(XML, contact_model=contact_model, dtype=F64)
    state = torchsim.init(sys, torch.tensor(m.qpos0)[None], torch.zeros(1, sys.nv, dtype=F64))
    ctrl = torch.zeros(1, 0, dtype=F64)
    for _ in range(500):
        state = torchsim.step(sys, state, ctrl)
    ours = torchsim.sensordata(sys, state, ctrl)[0]
    print(contact_model, ours.numpy().round(4), d.sensordata.round(4))
    assert d.sensordata[1] == pytest.approx(9.81, rel=0.01) and d.sensordata[2] > 1.0  # the zones do split
    assert torch.allclose(ours, torch.tensor(d.sensordata), atol=0.005 * 19.62)
    assert (ours[d.sensordata == 0] == 0).all()


def test_touch_needs_the_controls():
    sys = torchsim.load_mjcf(XML, dtype=F64)
    state = torchsim.init(sys, sys.q0[None].clone(), torch.zeros(1, sys.nv, dtype=F64))
    with pytest.raises(ValueError, match="touch sensors read forces that depend on the controls"):
        torchsim.sensordata(sys, state)
