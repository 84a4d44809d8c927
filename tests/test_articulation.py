"""The joint-space inertia of the kinematic tree (``torchsim.articulation``) against MuJoCo's (float64, CPU).

Where the model has hinges and slides only, torchsim's columns are MuJoCo's dofs, so ``M`` must equal ``mj_fullM``
less armature entry by entry. With free and ball joints torchsim's basis for them differs (world axes, a free body
turning about its COM), so what is compared is what does not depend on the basis: the bodies' mobility ``J M^-1
J^T``, every body's COM velocity and angular velocity per unit impulse and moment on every body (``mj_jac`` at
torchsim's COMs for MuJoCo's ``J``). Both at random poses, where every term of ``M`` is in play. Agreement is to
rounding: 1e-16 relative measured for ``M``, 1e-12 for the mobility (1e-9 on the pusher, whose 5 g wrist links
make ``M`` ill-conditioned), so the tolerances are 1e-12 and 1e-7.
"""

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from models import F64, REPO, random_q
from torchsim import articulation, pipeline, rigid
from torchsim.kinematics import joint_frames

ASSETS = REPO / "envs" / "assets"

# a ball joint carrying a hinge, a slide carrying a hinge, and a free body carrying a ball joint
BALL_SLIDE_FREE = """<mujoco><worldbody>
  <body pos="0 0 1"><joint type="ball"/><geom type="capsule" fromto="0 0 0 0.3 0.1 0" size="0.03" mass="1.5"/>
    <body pos="0.3 0.1 0"><joint type="hinge" axis="0 0.6 0.8"/>
      <geom type="box" pos="0.1 0 0.05" size="0.1 0.04 0.02" mass="0.7"/></body></body>
  <body pos="1 0 1"><joint type="slide" axis="1 0 0"/><geom type="sphere" size="0.05" mass="2"/>
    <body pos="0 0 -0.2"><joint type="hinge" axis="1 1 0"/><geom type="capsule" fromto="0 0 0 0 0.2 -0.3" size="0.02"/>
    </body></body>
  <body pos="-1 0 1"><freejoint/><geom type="box" size="0.2 0.1 0.05" pos="0.05 0 0" mass="3"/>
    <body pos="0.2 0 0"><joint type="ball"/><geom type="sphere" pos="0.1 0.1 0" size="0.06" mass="0.4"/></body>
  </body></worldbody></mujoco>"""


def at_random_pose(xml: str, seed: int = 0):
    """MuJoCo's model, data and ``mj_fullM`` less armature at a random pose, and torchsim's System and
    :class:`articulation.Articulation` at the same pose."""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    d.qpos[:] = random_q(m, 1, np.random.default_rng(seed))[0]
    mujoco.mj_forward(m, d)
    inertia = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, inertia)
    sys = torchsim.load_mjcf(xml, dtype=F64, contact_model="articulated")
    state = torchsim.init(sys, torch.tensor(d.qpos[None].copy()), torch.zeros(1, m.nv, dtype=F64))
    bodies, _ = pipeline.to_lanes(state, torch.zeros(1, sys.nu, dtype=F64))
    rot = rigid.inverse_inertia(sys, bodies.x_quat, rigid.body_inverse_inertia(sys)).rot
    model = articulation.articulation(sys, bodies, joint_frames(sys, bodies, rot=rot), rot)
    return m, d, inertia - np.diag(m.dof_armature), sys, bodies, model


@pytest.mark.parametrize("name", ["hopper.xml", "walker2d.xml", "reacher.xml", "pusher.xml"])
def test_hinge_and_slide_inertia_is_mujocos(name):
    """The hopper's and walker's roots are two slides and a hinge in one joint; the reacher and pusher are arms."""
    m, _, expected, sys, _, model = at_random_pose((ASSETS / name).read_text())
    order = sys.dof_qvel.numpy()
    ours = model.inertia[:, :, 0].numpy()
    assert ours.shape == (m.nv, m.nv)
    np.testing.assert_allclose(ours, expected[np.ix_(order, order)], rtol=0, atol=1e-12 * np.abs(expected).max())


@pytest.mark.parametrize("xml", [(ASSETS / "ant.xml").read_text(), (ASSETS / "humanoid.xml").read_text(),
                                 BALL_SLIDE_FREE], ids=["ant", "humanoid", "ball-slide-free"])
def test_body_mobility_is_mujocos(xml):
    """The humanoid has 2- and 3-hinge joints on one body (abdomen, hips); the scene a ball joint on the world and
    one on a free body."""
    m, d, inertia, sys, bodies, model = at_random_pose(xml, seed=1)
    members = sys.mjbody_body.tolist()
    n = sys.num_bodies
    jac, lin, ang = np.zeros((6 * n, m.nv)), np.zeros((3, m.nv)), np.zeros((3, m.nv))
    for b in range(n):
        mujoco.mj_jac(m, d, lin, ang, bodies.x_pos[:, b, 0].numpy(), members.index(b))
        jac[6 * b:6 * b + 6] = np.concatenate((lin, ang))
    expected = jac @ np.linalg.solve(inertia, jac.T)
    ours_jac = torch.cat((model.vel[..., 0], model.ang[..., 0])).permute(2, 0, 1).reshape(6 * n, -1).numpy()
    ours = ours_jac @ np.linalg.solve(model.inertia[:, :, 0].numpy(), ours_jac.T)
    np.testing.assert_allclose(ours, expected, rtol=0, atol=1e-7 * np.abs(expected).max())
