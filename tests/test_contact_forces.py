"""``torchsim.contact_forces`` against MuJoCo's ``mj_contactForce`` and ``qfrc_constraint`` on bodies at rest: a box
on a plane and the Ant standing from its home pose under zero control (soft contacts, its env's default, and
articulated ones), both settled in each simulator first."""

from typing import NamedTuple

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from models import ANT, F64

BOX = """
<mujoco><option timestep="0.002"/><worldbody><geom type="plane" size="10 10 1"/>
  <body pos="0.1 -0.2 0.3"><freejoint/><geom type="box" size="0.2 0.1 0.05" mass="2"/></body>
</worldbody></mujoco>"""


def _mujoco_forces_per_body(m: mujoco.MjModel, d: mujoco.MjData) -> dict[str, np.ndarray]:
    """World-frame contact force on each body touching the world [N], summed over its contacts."""
    mujoco.mj_forward(m, d)
    wrench, per_body = np.zeros(6), {}
    for i in range(d.ncon):
        c = d.contact[i]
        mujoco.mj_contactForce(m, d, i, wrench)  # in the contact frame, on geom2 from geom1
        on_geom2 = c.frame.reshape(3, 3).T @ wrench[:3]
        touching, sign = (c.geom2, 1.0) if m.geom_bodyid[c.geom1] == 0 else (c.geom1, -1.0)
        name = m.body(m.geom_bodyid[touching]).name
        per_body[name] = per_body.get(name, 0.0) + sign * on_geom2
    return per_body


def _torchsim_forces_per_body(sys: torchsim.System, state: torchsim.State, ctrl: torch.Tensor, names: list[str]):
    forces = torchsim.contact_forces(sys, state, ctrl)
    per_body = {}
    for k in torch.nonzero(forces.active[0]).flatten().tolist():
        name = names[int(forces.body_a[k])]
        per_body[name] = per_body.get(name, 0.0) + forces.force[0, k].numpy()
    return per_body


class Settled(NamedTuple):
    """torchsim's and MuJoCo's contact forces per body after settling, and each simulator's model and state."""

    ours: dict
    theirs: dict
    m: mujoco.MjModel
    d: mujoco.MjData
    sys: torchsim.System
    state: torchsim.State
    ctrl: torch.Tensor


def _settled(xml_or_path, steps: int, contact_model: str, keyframe: bool) -> Settled:
    """Both simulators after ``steps`` steps at rest from the same start."""
    m = mujoco.MjModel.from_xml_path(str(xml_or_path)) if keyframe else mujoco.MjModel.from_xml_string(xml_or_path)
    d = mujoco.MjData(m)
    if keyframe:
        mujoco.mj_resetDataKeyframe(m, d, 0)
    start = d.qpos.copy()
    for _ in range(steps):
        mujoco.mj_step(m, d)
    sys = torchsim.load_mjcf(str(xml_or_path), contact_model=contact_model, dtype=F64)
    state = torchsim.init(sys, torch.tensor(start)[None], torch.zeros(1, sys.nv, dtype=F64))
    ctrl = torch.zeros(1, sys.nu, dtype=F64)
    for _ in range(steps):
        state = torchsim.step(sys, state, ctrl)
    return Settled(_torchsim_forces_per_body(sys, state, ctrl, sys.body_names), _mujoco_forces_per_body(m, d), m, d,
                   sys, state, ctrl)


@pytest.mark.parametrize("contact_model", ["impulse", "soft", "articulated"])
def test_resting_box_holds_its_weight_like_mujoco(contact_model):
    """A 2 kg box resting flat: the contacts push up with its weight, no friction, as in MuJoCo (to 0.5 %: the
    readout is one substep's impulse over its length, and the box still settles by ~1e-4 m/s)."""
    ours, theirs, m, *_ = _settled(BOX, 1000, contact_model, keyframe=False)
    weight = m.body_subtreemass[0] * -m.opt.gravity[2]
    for forces in (ours, theirs):
        (total,) = forces.values()
        assert total[2] == pytest.approx(weight, rel=5e-3)
        assert np.abs(total[:2]).max() < 1e-3 * weight


@pytest.fixture(scope="module", params=["soft", "articulated"])
def ant_at_rest(request):
    return request.param, _settled(ANT, 300, request.param, keyframe=True)


# the share of the largest that torchsim's friction and hinge torques at rest may miss MuJoCo's by: the soft
# contacts act on the touching links alone and leave the joint springs to carry the rest; the articulated model
# solves joints, limits and contacts in MuJoCo's one system (docstrings below)
REST_TOLERANCE = {"soft": 0.1, "articulated": 0.01}


def test_resting_ant_feet_carry_mujocos_normal_forces(ant_at_rest):
    """The Ant settled from its home pose (3 s, zero control, soft or articulated contacts): each foot's normal
    force is MuJoCo's within 1 % (measured: 2.234 N each on both, MuJoCo 2.234), and the four carry the Ant's
    weight."""
    _, (ours, theirs, m, *_) = ant_at_rest
    assert sorted(ours) == sorted(theirs)
    for foot, force in theirs.items():
        print(f"{foot}: torchsim {np.round(ours[foot], 3)}, MuJoCo {np.round(force, 3)} N")
        assert ours[foot][2] == pytest.approx(force[2], rel=0.01)
    assert sum(f[2] for f in ours.values()) == pytest.approx(m.body_subtreemass[0] * 9.81, rel=0.01)


def test_resting_ant_feet_carry_mujocos_friction(ant_at_rest):
    """Each foot's friction is MuJoCo's within 10 % on soft contacts, 1 % on articulated ones (measured: 1.124 N in
    the leg's vertical plane on soft contacts, 1.1114 N on articulated ones, MuJoCo 1.1114 N). On soft contacts it
    is the step's mean: the friction of one soft substep alone is 1.37 N, 35 degrees off that plane, and alternates
    from substep to substep (``torchsim.contact_forces``)."""
    contact_model, (ours, theirs, *_) = ant_at_rest
    for foot, force in theirs.items():
        assert np.linalg.norm(ours[foot][:2] - force[:2]) < REST_TOLERANCE[contact_model] * np.linalg.norm(force[:2])


def test_resting_ant_hinges_carry_mujocos_constraint_torques(ant_at_rest):
    """The torque the contacts put on each hinge, ``J^T f`` (MuJoCo's Jacobians at torchsim's settled pose), against
    MuJoCo's ``qfrc_constraint`` at its own (no joint limit is active there, so that is its contacts' alone): the
    ankles carry 0.1294 N m (soft) and 0.1233 (articulated) where MuJoCo's carry 0.1234, the hips 0 as MuJoCo's
    (each leg's friction lies in its plane). Soft contacts within 10 % of the largest: the ankles settle 0.008 rad
    off MuJoCo's (the Ant rests 1.8 mm low, ``tests/test_rest_heights.py``), which moves their lever, and the
    friction that holds the splayed legs at rest is 1.2 % over MuJoCo's. Articulated ones within 1 %: their torso
    rests 24 um from MuJoCo's. The free root's row is the Ant's weight."""
    contact_model, (_, _, m, d, sys, state, ctrl) = ant_at_rest
    forces = torchsim.contact_forces(sys, state, ctrl)
    at_ours = mujoco.MjData(m)
    at_ours.qpos[:] = state.q[0].numpy()
    mujoco.mj_kinematics(m, at_ours)
    mujoco.mj_comPos(m, at_ours)
    ours, jac = np.zeros(m.nv), np.zeros((3, m.nv))
    for k in torch.nonzero(forces.active[0]).flatten().tolist():
        mujoco.mj_jac(m, at_ours, jac, None, forces.pos[0, k].numpy(), m.body(sys.body_names[forces.body_a[k]]).id)
        ours += jac.T @ forces.force[0, k].numpy()
    theirs = d.qfrc_constraint
    print(f"hinges: torchsim {np.round(ours[6:], 4)}, MuJoCo {np.round(theirs[6:], 4)} N m")
    assert not any(d.efc_type == mujoco.mjtConstraint.mjCNSTR_LIMIT_JOINT)
    np.testing.assert_allclose(ours[6:], theirs[6:], atol=REST_TOLERANCE[contact_model] * np.abs(theirs[6:]).max())
    assert ours[2] == pytest.approx(theirs[2], rel=0.01)


def test_xpbd_says_it_has_no_readout():
    sys = torchsim.load_mjcf(BOX, method="xpbd", dtype=F64)
    state = torchsim.init(sys, sys.q0[None].clone(), torch.zeros(1, 6, dtype=F64))
    with pytest.raises(NotImplementedError, match="spring method only"):
        torchsim.contact_forces(sys, state, torch.zeros(1, 0, dtype=F64))
