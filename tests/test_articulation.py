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
from torchsim import articulation, pipeline, rigid, spatial, tree_solve
from torchsim.kinematics import forward, joint_frames, with_world

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


def _moving(xml: str, seed: int):
    """:func:`at_random_pose` with random velocities ``qd`` (MuJoCo's qvel) too: the System, MuJoCo's model, ``q``,
    ``qd``, and the bodies (lanes), their frames, articulation and columns' rates."""
    m = mujoco.MjModel.from_xml_string(xml)
    rng = np.random.default_rng(seed)
    q, qd = random_q(m, 1, rng)[0], rng.normal(0.0, 1.0, m.nv)
    sys = torchsim.load_mjcf(xml, dtype=F64, contact_model="articulated")
    bodies = with_world(*forward(sys, torch.tensor(q[None]), torch.tensor(qd[None])))
    rot = rigid.inverse_inertia(sys, bodies.x_quat, rigid.body_inverse_inertia(sys)).rot
    frames = joint_frames(sys, bodies, rot=rot)
    model = articulation.articulation(sys, bodies, frames, rot)
    return sys, m, q, qd, bodies, frames, model, tree_solve.column_rates(sys, bodies, frames)


@pytest.mark.parametrize("xml", [(ASSETS / "humanoid.xml").read_text(), BALL_SLIDE_FREE],
                         ids=["humanoid", "ball-slide-free"])
def test_the_columns_rates_move_the_bodies_at_their_velocities(xml):
    """``J qd`` with the columns' rates read from moving bodies is their velocities (to rounding, 1.4e-12 measured):
    the Jacobian's columns are the dofs' axes, also for the humanoid's 3-hinge hips, whose joint frames hold dual
    rows."""
    sys, _, _, _, bodies, _, model, rates = _moving(xml, seed=2)
    n = sys.num_bodies
    np.testing.assert_allclose((model.vel * rates[:, None]).sum(1), bodies.xd_vel[:, :n], rtol=0, atol=1e-10)
    np.testing.assert_allclose((model.ang * rates[:, None]).sum(1), bodies.xd_ang[:, :n], rtol=0, atol=1e-10)


@pytest.mark.parametrize("xml", [(ASSETS / "ant.xml").read_text(), (ASSETS / "hopper.xml").read_text(),
                                 (ASSETS / "humanoid.xml").read_text(), BALL_SLIDE_FREE],
                         ids=["ant", "hopper", "humanoid", "ball-slide-free"])
def test_velocity_product_is_the_rate_of_the_bodies_velocities(xml):
    """``d/dt(J) qd`` (``articulation.velocity_product``) against a central difference of the bodies' velocities
    along the motion (MuJoCo's ``mj_integratePos``, its ``qd`` held). MuJoCo's qvel holds a free body's frame-origin
    velocity and a ball joint's rate in its child's frame where the columns hold the COM's velocity and the rate in
    world axes, so the terms that turns into are taken off the difference: ``w x (w x c)`` on a free body's subtree
    (``c`` its COM offset), and ``w_k x w_rel`` turning a ball's subtree about its anchor (``w_k`` its child's
    angular velocity). Measured agreement 1e-9 of the largest term at ``eps`` 1e-6 (the difference's truncation)."""
    sys, m, q, qd, bodies, frames, model, rates = _moving(xml, seed=3)
    eps, n = 1e-6, sys.num_bodies
    velocities = []
    for sign in (1.0, -1.0):
        moved = q.copy()
        mujoco.mj_integratePos(m, moved, qd, sign * eps)
        at = forward(sys, torch.tensor(moved[None]), torch.tensor(qd[None]))
        velocities.append((at.xd_vel[..., 0], at.xd_ang[..., 0]))
    finite_lin, finite_ang = ((a - b) / (2 * eps) for a, b in zip(*velocities))
    first_free_column = model.inertia.shape[0] - 6 * sys.free_body.shape[0]
    for k, body in enumerate(sys.free_body.tolist()):  # the COM velocity held, not the origin's: w x (w x c)
        w = bodies.xd_ang[:, body, 0]
        c = spatial.quat_rotate(bodies.x_quat[:, body, 0], sys.body_ipos[body])
        subtree = sys.tree_moves[first_free_column + 6 * k]  # (N,): the bodies the free body carries
        finite_lin = finite_lin - subtree * torch.linalg.cross(w, torch.linalg.cross(w, c))[:, None]
    for k, joint in enumerate(sys.ball_joint.tolist()):
        child, parent = sys.jnt_child[joint], sys.jnt_parent[joint]
        w_child = bodies.xd_ang[:, child, 0]
        turn = torch.linalg.cross(w_child, w_child - bodies.xd_ang[:, parent, 0])  # d/dt of the world rate, MuJoCo's
        subtree = sys.tree_moves[sys.dof_flat.shape[0] + 3 * k]
        anchor = bodies.x_pos[:, child, 0] + frames.r_child[:, joint, 0]
        finite_ang = finite_ang - subtree * turn[:, None]
        arm = bodies.x_pos[:, :n, 0] - anchor[:, None]
        finite_lin = finite_lin - subtree * torch.linalg.cross(turn[:, None].expand_as(arm), arm, dim=0)
    product = articulation.velocity_product(sys, model, bodies, frames, rates)
    scale = max(finite_lin.abs().max(), finite_ang.abs().max())
    np.testing.assert_allclose(product.xd_vel[:, :n, 0], finite_lin, rtol=0, atol=1e-7 * scale)
    np.testing.assert_allclose(product.xd_ang[:, :n, 0], finite_ang, rtol=0, atol=1e-7 * scale)
