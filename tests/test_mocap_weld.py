"""Mocap bodies and ``<weld>``/``<connect>`` equality constraints (``torchsim.welds``) against MuJoCo 4.0: the
residuals and their rates at a random state; a body welded or connected to the world moves and rests as MuJoCo's
does; a body and an arm welded to a mocap body follow it as MuJoCo's do; constraints that move nothing dropped; per-env mocap targets in the step kernel; refusals;
``<skin>`` ignored with a warning."""

import warnings

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from torchsim import pipeline, spatial, welds
from torchsim.execution.kernel import emit_cuda
from torchsim.execution.kernel.step import StepKernel
from models import F64, kernel_beside_reference
from torchsim.envs.base import TorchsimEnv

# every kind of side: bodies with a COM away from their frame, a fused child, the world, a mocap body and a jointless
# child of it, sites; relpose and torquescale
SIDES = """
<mujoco><worldbody>
  <body name="mocap" mocap="true" pos="0.3 0.1 1.2" quat="0.9 0.1 0.3 0.2">
    <geom type="box" size=".02 .02 .02" contype="0" conaffinity="0"/>
    <body name="mchild" pos="0.1 0 0" euler="0 0.5 0"><site name="ms" pos="0.01 0.02 0.03"/></body></body>
  <body name="a" pos="0 0 1"><freejoint/><geom type="box" size=".1 .05 .03" mass="1"/>
    <site name="sa" pos="0.05 0 0.01" euler="0.2 0.1 0"/>
    <body name="a2" pos="0 0.2 0"><joint type="hinge" axis="1 0 0"/>
      <geom type="capsule" size=".02" fromto="0 0 0 0 0.2 0"/></body></body>
  <body name="b" pos="0.5 0 1" euler="0.3 0.2 0.1"><freejoint/><geom type="sphere" size=".05" pos="0.02 0 0"/></body>
</worldbody><equality>
  <connect body1="a" body2="b" anchor="0.1 0.2 0.3"/>
  <weld body1="a2" body2="b" relpose="0.1 0.2 0.3 0.8 0.1 0.2 0.3" anchor="0.05 0 0" torquescale="0.7"/>
  <weld body1="mocap" body2="a" solref="0.02 1" solimp="0.9 0.95 0.001"/>
  <weld body1="mchild" body2="a2"/>
  <connect body1="a2" anchor="0.1 0 0"/>
  <weld body1="b"/>
  <connect site1="ms" site2="sa"/>
  <weld site1="sa" site2="ms" torquescale="2"/>
</equality></mujoco>"""


def _lanes_bodies(sys, qpos, qvel):
    state = pipeline.init(sys, torch.tensor(qpos[None]), torch.tensor(qvel[None]))
    return pipeline.to_lanes(state, torch.zeros(1, sys.nu, dtype=F64))[0], state


def _with_mocap(sys, d):
    return sys.replace(mocap_pos=torch.tensor(d.mocap_pos[None]), mocap_quat=torch.tensor(d.mocap_quat[None]))


def test_residuals_and_rates_match_mujoco():
    """MuJoCo's ``efc_pos`` and ``efc_J qvel`` of every weld and connect row, at a random state and mocap pose, to
    float64 rounding; and the rows' inverse inertias ``A0`` are MuJoCo's ``efc_diagApprox`` (as ``R`` implies)."""
    m = mujoco.MjModel.from_xml_string(SIDES)
    m.opt.jacobian = mujoco.mjtJacobian.mjJAC_DENSE
    d = mujoco.MjData(m)
    rng = np.random.default_rng(0)
    d.qpos[:], d.qvel[:] = m.qpos0 + rng.normal(0, 0.1, m.nq), rng.normal(0, 1, m.nv)
    d.mocap_pos[:] = m.body_pos[1] + 0.1
    d.mocap_quat[:] = rng.normal(size=4)  # unnormalized, as a user may set it: MuJoCo normalizes it, and so do we
    mujoco.mj_forward(m, d)
    sys = _with_mocap(torchsim.load_mjcf(SIDES, dtype=F64), d)
    r, v, *_ = welds.residuals(sys, _lanes_bodies(sys, d.qpos, d.qvel)[0])
    rows = [3 if m.eq_type[e] == mujoco.mjtEq.mjEQ_CONNECT else 6 for e in range(m.neq)]
    jac = d.efc_J.reshape(d.nefc, m.nv)
    start = np.cumsum([0] + rows)
    for e, n in enumerate(rows):
        efc = slice(start[e], start[e] + n)
        np.testing.assert_allclose(r[:n, e, 0].numpy(), d.efc_pos[efc], atol=1e-12)
        np.testing.assert_allclose(v[:n, e, 0].numpy(), jac[efc] @ d.qvel, atol=1e-12)
        imp = d.efc_KBIP.reshape(-1, 4)[start[e], 2]
        diag = d.efc_R[efc] * imp / (1 - imp)  # MuJoCo's R = (1 - imp) / imp diagApprox
        a0 = sys.weld_invweight[e].sum(0).repeat_interleave(3)[:n].numpy()
        np.testing.assert_allclose(a0, diag, rtol=1e-9)


# a free box whose COM is off its frame, held from the world: {eq}
HANG = """
<mujoco><option timestep="0.002"/><worldbody>
  <body name="box" pos="0.1 0 1"><freejoint/>
    <geom type="box" size=".1 .05 .03" pos="0.05 0 0" mass="1" contype="0" conaffinity="0"/></body>
</worldbody><equality>{eq}</equality></mujoco>"""


@pytest.mark.parametrize("eq,path_tolerance", [
    # a weld to the world origin, 1.1 m from the box: the box swings about it, against the weld's soft rotation rows
    ('<weld body1="box" solimp="0.9 0.95 0.001" solref="0.02 1"/>', 5e-4),
    # a connect 0.1 m above the COM: the box sags 0.37 mm and hangs still
    ('<connect body1="box" anchor="0.05 0 0.1" solref="0.02 1"/>', 2e-5),
], ids=["weld", "connect"])
def test_held_body_moves_as_mujocos_does(eq, path_tolerance):
    """A box held from the world under gravity for 1 s. The impulse is MuJoCo's soft constraint on the bare bodies
    (``a0`` from the other forces, ``A`` the body's own), which for a free body is MuJoCo's constraint: the weld's
    box swings 0.12 rad as MuJoCo's does, its position within ``path_tolerance`` of MuJoCo's at every step (measured
    0.24 mm: MuJoCo steps at 2 ms, torchsim at 0.5 ms), and the connect's box rests at MuJoCo's sag (0.37 mm) to
    1e-8 m (measured 4e-10: at rest the integrators no longer matter)."""
    xml = HANG.format(eq=eq)
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    sys = torchsim.load_mjcf(xml, dtype=F64)
    state = pipeline.init(sys, sys.q0[None], torch.zeros(1, sys.nv, dtype=F64))
    worst = 0.0
    for _ in range(500):
        mujoco.mj_step(m, d)
        state = torchsim.step(sys, state, torch.zeros(1, 0, dtype=F64))
        worst = max(worst, np.abs(state.q[0, :3].numpy() - d.qpos[:3]).max())
    assert np.abs(d.qpos - m.qpos0).max() > (0.1 if "weld" in eq else 3e-4)  # it did move
    assert worst < path_tolerance
    if "connect" in eq:
        np.testing.assert_allclose(state.q[0].numpy(), d.qpos, atol=1e-8)
    assert not state.diverged.any()


# a free body welded to a mocap body; the mocap body has a (non-colliding) marker geom
FOLLOW = """
<mujoco><option timestep="0.002"/><worldbody>
  <body name="target" mocap="true" pos="0 0 1"><geom type="sphere" size=".01" contype="0" conaffinity="0"/></body>
  <body name="ball" pos="0 0 1"><freejoint/><geom type="box" size=".05 .03 .02" mass="0.5"/></body>
</worldbody><equality><weld body1="target" body2="ball" solimp="0.9 0.95 0.001" solref="0.02 1"/></equality>
</mujoco>"""


def _mujoco_follow(xml, target_pos, target_quat, seconds, body):
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    d.mocap_pos[:], d.mocap_quat[:] = target_pos, target_quat
    out = []
    for _ in range(round(seconds / m.opt.timestep)):
        mujoco.mj_step(m, d)
        out.append(d.xpos[body].copy())
    return np.array(out)


def _torchsim_follow(sys, target_pos, target_quat, seconds, body):
    sys = sys.replace(mocap_pos=torch.tensor(target_pos[None]), mocap_quat=torch.tensor(target_quat[None]))
    state = pipeline.init(sys, sys.q0[None], torch.zeros(1, sys.nv, dtype=F64))
    out = []
    for _ in range(round(seconds / sys.timestep)):
        state = torchsim.step(sys, state, torch.zeros(1, sys.nu, dtype=F64))
        out.append(_frame_pos(sys, state, body))
    return np.array(out), state


def _frame_pos(sys, state, mj_body):
    """MuJoCo body ``mj_body``'s frame origin in the world (its fused body's pose and offset)."""
    b = sys.mjbody_body[mj_body]
    return (state.x_pos[0, b] + spatial.quat_rotate(state.x_quat[0, b][:, None],
                                                    sys.mjbody_pos[mj_body][:, None])[:, 0]).numpy()


def test_body_follows_mocap_as_mujocos_does():
    """The mocap target jumps 5 cm and turns 0.4 rad: the welded box chases it as MuJoCo's does (gravity on). On a
    free body welded at its frame the rows' inverse inertia is the body's own, so the approach is MuJoCo's soft
    constraint's: the paths agree to 5% of the jump at every step (their integrators differ: MuJoCo's 2 ms Euler
    step against torchsim's 0.5 ms substeps, on a 20 ms time constant), and both end within 0.5 mm of it."""
    sys = torchsim.load_mjcf(FOLLOW, dtype=F64)
    assert sys.mocap_pos.shape == (1, 3) and sys.welds
    jump = np.array([0.05, -0.03, 0.02])
    target = np.array([0.0, 0.0, 1.0]) + jump
    turn = np.array([np.cos(0.2), np.sin(0.2), 0.0, 0.0])
    expected = _mujoco_follow(FOLLOW, target, turn, 0.3, body=2)
    got, state = _torchsim_follow(sys, target, turn, 0.3, body=2)
    assert np.abs(got - expected).max() < 0.05 * np.linalg.norm(jump)
    assert np.linalg.norm(got[-1] - target) < 5e-4 and np.linalg.norm(expected[-1] - target) < 5e-4
    assert not state.diverged.any()


# a gymnasium-robotics-style scene: a 3-hinge arm whose gripper is welded to a mocap body (Fetch's weld parameters),
# a table under it
ARM = """
<mujoco><option timestep="0.002"/>
  <default><joint damping="1" armature="0.01"/></default>
  <worldbody>
    <geom name="floor" type="plane" size="2 2 .1"/>
    <body name="mocap" mocap="true" pos="0.4 0 0.5">
      <geom type="box" size=".005 .005 .005" contype="0" conaffinity="0" rgba="0 .5 0 .7"/></body>
    <body name="base" pos="0 0 0.5">
      <joint name="yaw" type="hinge" axis="0 0 1"/>
      <geom type="capsule" size=".04" fromto="0 0 0 0.2 0 0" mass="2"/>
      <body name="upper" pos="0.2 0 0"><joint name="pitch" type="hinge" axis="0 1 0"/>
        <geom type="capsule" size=".03" fromto="0 0 0 0.15 0 0" mass="1"/>
        <body name="gripper" pos="0.2 0 0"><joint name="wrist" type="hinge" axis="0 1 0"/>
          <geom type="box" size=".03 .03 .03" mass="0.3"/></body></body></body>
  </worldbody>
  <equality><weld body1="mocap" body2="gripper" solimp="0.9 0.95 0.001" solref="0.02 1"/></equality>
</mujoco>"""


@pytest.mark.parametrize("method,path_tolerance,rest_tolerance", [("spring", 3e-3, 5e-4), ("xpbd", 2.5e-2, 5e-3)])
def test_arm_follows_mocap_as_mujocos_does(method, path_tolerance, rest_tolerance):
    """The Fetch-style way to drive an arm: move the mocap target 8 cm and turn it, and the gripper follows it through
    the arm's damped joints as MuJoCo's does: the paths within ``path_tolerance`` at every step and at rest after
    0.5 s within ``rest_tolerance`` of MuJoCo's, the arm together. The weld acts on the bare gripper (the spring
    method's with its hinge's armature) and the method's joints carry it to the arm, where MuJoCo solves the chain at once. With
    springs the joints' forces are part of the weld's ``a0``, and it rests where MuJoCo's does (measured: paths
    2.9 mm apart, 0.04 mm at rest);
    XPBD's joints are projections after the forces, so its weld holds the arm's weight only through the residual
    and the gripper rests 3.9 mm low (paths 18 mm apart while it swings)."""
    sys = torchsim.load_mjcf(ARM, dtype=F64, method=method)
    yaw, pitch = 0.15, 0.3  # a pose the arm reaches: yawed, the upper link pitched down, the wrist level
    reach = 0.2 + 0.2 * np.cos(pitch)
    target = np.array([reach * np.cos(yaw), reach * np.sin(yaw), 0.5 - 0.2 * np.sin(pitch)])
    level = np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])
    gripper = mujoco.mj_name2id(mujoco.MjModel.from_xml_string(ARM), mujoco.mjtObj.mjOBJ_BODY, "gripper")
    expected = _mujoco_follow(ARM, target, level, 0.5, body=gripper)
    got, state = _torchsim_follow(sys, target, level, 0.5, body=gripper)
    assert np.linalg.norm(expected[-1] - expected[0]) > 0.05  # it did move
    assert np.linalg.norm(got - expected, axis=-1).max() < path_tolerance
    assert np.linalg.norm(got[-1] - expected[-1]) < rest_tolerance
    assert not state.diverged.any()


def test_gradient_through_a_weld_to_its_mocap_target():
    """The reference step is differentiable in the mocap target (e.g. to plan a target path by gradient): the
    gradient of the gripper's position after 10 steps agrees with central differences (step 1e-6) to 1e-8
    (measured 1e-11)."""
    base = torchsim.load_mjcf(ARM, dtype=F64)

    def gripper_after_steps(target):
        sys = base.replace(mocap_pos=target[None, None], mocap_quat=base.mocap_quat[None])
        state = pipeline.init(sys, sys.q0[None], torch.zeros(1, sys.nv, dtype=F64))
        for _ in range(10):
            state = torchsim.step(sys, state, torch.zeros(1, sys.nu, dtype=F64))
        return state.x_pos[0, -1].sum()

    target = torch.tensor([0.38, 0.05, 0.45], dtype=F64, requires_grad=True)
    grad, = torch.autograd.grad(gripper_after_steps(target), target)
    with torch.no_grad():
        central = torch.stack([(gripper_after_steps(target + 1e-6 * e) - gripper_after_steps(target - 1e-6 * e)) / 2e-6
                               for e in torch.eye(3, dtype=F64)])
    assert grad.abs().min() > 0.1
    torch.testing.assert_close(grad, central, atol=1e-8, rtol=0)


def test_per_env_mocap_targets_in_the_step_kernel():
    """Per-env mocap poses are inputs of the step kernel: two envs chasing two targets step as the reference step
    does, and moving the targets reuses the kernel."""
    sys = torchsim.load_mjcf(ARM, dtype=F64)
    targets = torch.tensor([[[0.38, 0.05, 0.45]], [[0.4, -0.04, 0.52]]], dtype=F64)
    quats = torch.tensor([[[1.0, 0, 0, 0.1]], [[0.98, 0, 0.2, 0]]], dtype=F64)
    per_env = sys.replace(mocap_pos=targets, mocap_quat=quats)
    start = pipeline.init(sys, sys.q0.expand(2, -1), torch.zeros(2, sys.nv, dtype=F64))
    _, expected, got = kernel_beside_reference(per_env, start)
    assert (expected.x_pos - start.x_pos).abs().max() > 1e-3
    assert (got.x_pos - expected.x_pos).abs().max() < 1e-9


def test_per_env_mocap_targets_in_the_cuda_kernel(monkeypatch, tmp_path):
    """The same step emitted as CUDA C (one thread an env), its source compiled for the host as
    tests/test_strategies.py checks the GPU kernel: it steps two envs chasing two targets as the reference does."""
    monkeypatch.setenv("TORCHSIM_CACHE_DIR", str(tmp_path))
    sys = torchsim.load_mjcf(ARM, dtype=F64).replace(
        mocap_pos=torch.tensor([[[0.38, 0.05, 0.45]], [[0.4, -0.04, 0.52]]], dtype=F64),
        mocap_quat=torch.tensor([[[1.0, 0, 0, 0.1]], [[0.98, 0, 0.2, 0]]], dtype=F64))
    kernel = StepKernel(sys, emitter=emit_cuda)
    start = pipeline.init(sys, sys.q0.expand(2, -1), torch.zeros(2, sys.nv, dtype=F64))
    ctrl = torch.zeros(2, 0, dtype=F64)
    expected, got = start, start
    for _ in range(20):
        expected, got = torchsim.step(sys, expected, ctrl), kernel(sys, got, ctrl)
    assert (expected.x_pos - start.x_pos).abs().max() > 1e-3
    assert (got.x_pos - expected.x_pos).abs().max() < 1e-9


@pytest.mark.parametrize("xml,match", [
    (FOLLOW.replace('<geom type="sphere" size=".01" contype="0" conaffinity="0"/>',
                    '<body name="hanging"><joint type="hinge"/><geom size=".01" contype="0" conaffinity="0"/></body>'),
     "body 'hanging' is attached to mocap body 'target' by joints"),
])
def test_unsupported_mocap_uses_are_refused_by_name(xml, match):
    with pytest.raises(torchsim.UnsupportedMJCFError, match=match):
        torchsim.load_mjcf(xml)


@pytest.mark.parametrize("eq", [
    '<weld body1="target"/>',  # a mocap body and the world
    '<connect body1="ball" body2="stuck" anchor="0 0 0"/>',  # two bodies of one rigid body
])
def test_constraint_that_moves_nothing_is_dropped(eq):
    """MuJoCo drops a weld or connect whose Jacobian is empty; so does torchsim (a constraint inside one rigid body
    would otherwise twist it)."""
    xml = FOLLOW.replace('mass="0.5"/>', 'mass="0.5"/><body name="stuck" pos="0.1 0 0"><geom size=".01"/></body>')
    xml = xml.replace('<weld body1="target" body2="ball" solimp="0.9 0.95 0.001" solref="0.02 1"/>', eq)
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    assert m.neq == 1 and d.ne == 0
    sys = torchsim.load_mjcf(xml)
    assert not sys.welds and sys.weld_frame.shape == (0, 2)


SKIN = """
<mujoco><worldbody><body name="b"><freejoint/><geom size=".1"/></body></worldbody>
<deformable><skin name="s" vertex="0 0 0 .1 0 0 0 .1 0" face="0 1 2">
  <bone body="b" bindpos="0 0 0" bindquat="1 0 0 0" vertid="0 1 2" vertweight="1 1 1"/></skin></deformable>
</mujoco>"""


def test_skin_is_ignored_with_one_warning():
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sys = torchsim.load_mjcf(SKIN)
    skin = [w for w in caught if "<skin>" in str(w.message)]
    assert len(skin) == 1 and "no physics" in str(skin[0].message)
    assert sys.num_bodies == 1


class _ArmEnv(TorchsimEnv):
    """The ``ARM`` scene as an env (a yaw motor, so the action spec is not empty), observing the gripper."""

    frame_skip = 10  # 20 ms
    observation_size = 3
    named_bodies = ("gripper",)
    noise_q = noise_qd = ("uniform", 0.0)

    def _model_xml(self) -> str:
        return ARM.replace("</mujoco>", '<actuator><motor joint="yaw" gear="0.1"/></actuator></mujoco>')

    def _observation(self, state, ctrl):
        return self.mj_body_positions(state)[:, 0]

    def _reward(self, before, after, ctrl):
        return torch.zeros_like(after.q[:, 0])

    def _terminated(self, state):
        return torch.zeros_like(state.diverged)


def test_an_env_drives_each_envs_gripper_to_its_own_mocap_target():
    """``set_mocap`` gives each env its target; the welded grippers settle at them (the weld's sag under the arm's
    weight is ~0.1 mm here, see the arm test), and ``set_physics`` afterwards keeps the targets."""
    env = _ArmEnv(2, dtype=F64)
    yaw, pitch = torch.tensor([0.15, -0.2], dtype=F64), torch.tensor([0.3, -0.2], dtype=F64)
    upper = torch.stack([0.2 * yaw.cos(), 0.2 * yaw.sin(), torch.full_like(yaw, 0.5)], -1)  # reachable poses
    targets = (upper + 0.2 * torch.stack([pitch.cos() * yaw.cos(), pitch.cos() * yaw.sin(), -pitch.sin()], -1))[:, None]
    level = torch.stack([(yaw / 2).cos(), 0 * yaw, 0 * yaw, (yaw / 2).sin()], -1)[:, None]  # the wrist keeps it level
    env.set_mocap(pos=targets, quat=level)
    env.set_physics(mass_scale=torch.tensor([1.0, 1.2]))
    assert torch.equal(env.sys.mocap_pos, targets)
    td = env.reset()
    for _ in range(25):  # 0.5 s
        td = env.step_mdp(env.step(td.set("action", torch.zeros(2, 1, dtype=F64))))
    gripper = td["observation"]
    assert (gripper - targets[:, 0]).norm(dim=-1).max() < 5e-4  # measured 0.09 and 0.12 mm
    assert (gripper[0] - gripper[1]).norm() > 0.1  # each env its own target
    with pytest.raises(ValueError, match=r"mocap_pos must have shape \(2, 1, 3\)"):
        env.set_mocap(pos=targets[0])
