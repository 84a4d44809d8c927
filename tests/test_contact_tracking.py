"""Contact-rich scenes against MuJoCo over a short horizon: a tilted box dropped on a plane (it lands on a corner,
tumbles and slides) and a hopper-like chain (free torso, two hinged links) landing on its foot.

The reference is MuJoCo at a tenth of the model's time step; the yardstick is MuJoCo's own error at the model's
step, its dt sensitivity (about 2-3 mm here). Without friction torchsim's soft contacts stay within 3x that
yardstick. With friction they do not yet: each point's friction is one pass after the normal, sized for that point
alone (a joint normal-friction solve, 3 projected Gauss-Seidel sweeps, halves the box's error; it leaves the
chain's), and on a chain it stops the touching link alone, the rest following through the joints
(docs/physics.md, "Policy transfer"). Those cases hold today's measured error as a bound and the target as a strict
xfail."""

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from models import F64

BOX = """
<mujoco><option timestep="0.002"/><worldbody><geom type="plane" size="10 10 1" {contact}/>
  <body pos="0 0 0.5" euler="20 30 0"><freejoint/><geom type="box" size="0.2 0.15 0.05" mass="1" {contact}/></body>
</worldbody></mujoco>"""

CHAIN = """
<mujoco><option timestep="0.002"/><worldbody><geom type="plane" size="10 10 1" {contact}/>
  <body pos="0 0 0.6" euler="0 15 0"><freejoint/>
    <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.05" mass="3" {contact}/>
    <body pos="0.3 0 0"><joint type="hinge" axis="0 1 0" range="-60 60" damping="0.5"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.04" mass="1" {contact}/>
      <body pos="0 0 -0.3"><joint type="hinge" axis="0 1 0" range="-60 60" damping="0.5"/>
        <geom type="capsule" fromto="0 0 0 0.15 0 -0.1" size="0.04" mass="0.5" {contact}/>
      </body></body></body></worldbody></mujoco>"""

FRICTIONLESS = 'condim="1"'
FRICTION = 'friction="1 0.005 0.0001"'
STEPS = 300  # 0.6 s: the fall (~0.25 s), the landing and the settling


def _mujoco_root_positions(xml: str, divide: int) -> np.ndarray:
    """The free root's position ``(STEPS, 3)`` after each model step, MuJoCo at the model's step / ``divide``."""
    m = mujoco.MjModel.from_xml_string(xml)
    m.opt.timestep /= divide
    d = mujoco.MjData(m)
    rows = []
    for _ in range(STEPS):
        for _ in range(divide):
            mujoco.mj_step(m, d)
        rows.append(d.qpos[:3].copy())
    return np.array(rows)


def _torchsim_root_positions(xml: str, contact_model: str) -> np.ndarray:
    sys = torchsim.load_mjcf(xml, method="spring", contact_model=contact_model, dtype=F64)
    m = mujoco.MjModel.from_xml_string(xml)
    state = torchsim.init(sys, torch.tensor(m.qpos0)[None], torch.zeros(1, sys.nv, dtype=F64))
    ctrl = torch.zeros(1, sys.nu, dtype=F64)
    rows = []
    for _ in range(STEPS):
        state = torchsim.step(sys, state, ctrl)
        rows.append(state.q[0, :3].numpy().copy())
    return np.array(rows)


def _errors(scene: str, contact: str, contact_model: str) -> tuple[float, float]:
    """Max root position error [m] over the horizon: torchsim's and MuJoCo's at its own step, both against MuJoCo
    at a tenth of it."""
    xml = scene.format(contact=contact)
    reference = _mujoco_root_positions(xml, 10)
    own = np.abs(_mujoco_root_positions(xml, 1) - reference).max()
    ours = np.abs(_torchsim_root_positions(xml, contact_model) - reference).max()
    print(f"{contact_model}, {contact}: max root error {1000 * ours:.1f} mm, MuJoCo at its step {1000 * own:.1f} mm "
          f"({ours / own:.1f}x)")
    return ours, own


@pytest.mark.parametrize("scene", [BOX, CHAIN], ids=["box", "chain"])
def test_frictionless_landing_tracks_mujoco(scene):
    """Without friction the landing on soft contacts (the model the transfer work uses) follows MuJoCo within 3x
    MuJoCo's own dt sensitivity. Measured: box 0.7 mm against 2.6 mm, chain 6.7 mm against 2.9 mm (impulse
    contacts: 14.5 mm and 19.6 mm, 5.7x and 6.7x: each point's impulse is sized alone, so a body on two corners
    rebounds from both)."""
    ours, own = _errors(scene, FRICTIONLESS, "soft")
    assert ours < 3 * own


# Today's max root errors with friction 1, soft contacts (MuJoCo at its step: box 2.3 mm, chain 3.5 mm).
MEASURED_WITH_FRICTION_MM = {"box": 21.7, "chain": 63.8}


@pytest.mark.parametrize("scene, name", [(BOX, "box"), (CHAIN, "chain")], ids=["box", "chain"])
def test_landing_with_friction_stays_within_todays_error(scene, name):
    """A regression bound: today's measured error with friction plus 20 %."""
    ours, _ = _errors(scene, FRICTION, "soft")
    assert 1000 * ours < 1.2 * MEASURED_WITH_FRICTION_MM[name]


@pytest.mark.xfail(strict=True, reason="friction acts on the touching link alone: 9x (box) and 18x (chain) "
                                       "MuJoCo's dt sensitivity today")
@pytest.mark.parametrize("scene", [BOX, CHAIN], ids=["box", "chain"])
def test_landing_with_friction_tracks_mujoco(scene):
    ours, own = _errors(scene, FRICTION, "soft")
    assert ours < 3 * own
