"""Contacts of mocap bodies' geoms: a geom moves with its mocap body's per-env pose (``System.mocap_pos``/
``mocap_quat``) and collides with moving bodies as the static world's geoms do (at rest, taking no impulse), as
MuJoCo's mocap geoms do. Checked against MuJoCo's ``mj_collision`` at mocap poses set per env, and against MuJoCo's
rollouts of a cube carried by a rising mocap platform and pushed by a mocap paddle.
"""

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from models import F64, cached_third_party, kernel_beside_reference
from torchsim import lanes
from torchsim.collision import contacts
from torchsim.execution.kernel import emit_cuda
from torchsim.execution.kernel.step import StepKernel
from torchsim.io_mjcf import UnsupportedMJCFError
from torchsim.kinematics import with_world

ROUNDOFF = 1e-9  # [m] sphere-box and capsule-sphere contacts are exact: float64 round-off of the same geometry

PAIRS = """<mujoco><option gravity="0 0 0"/><worldbody>
  <body name="wall" mocap="true" pos="0 0 0.5"><geom name="wall" type="box" size="0.3 0.2 0.1"/></body>
  <body name="ball" mocap="true" pos="1 0 0.5">
    <geom name="ball" type="sphere" size="0.08" contype="2" conaffinity="2"/></body>
  <body name="free_ball" pos="0 0 0.62"><freejoint/><geom type="sphere" size="0.05" mass="1"/></body>
  <body name="free_rod" pos="1 0 0.6" euler="0 90 0"><freejoint/>
    <geom type="capsule" size="0.03 0.1" mass="1" contype="2" conaffinity="2"/></body>
  </worldbody></mujoco>"""
# per env: the two mocap bodies' positions and orientations (MuJoCo's w, x, y, z), each pair overlapping
MOCAP_POS = [[[0.0, 0.0, 0.5], [1.0, 0.0, 0.5]], [[0.05, -0.03, 0.51], [1.02, 0.05, 0.52]],
             [[-0.02, 0.04, 0.49], [0.96, -0.04, 0.55]]]
MOCAP_QUAT = [[[1.0, 0, 0, 0], [1.0, 0, 0, 0]], [[0.9659, 0, 0, 0.2588], [0.7071, 0.7071, 0, 0]],
              [[0.9848, 0.1736, 0, 0], [0.9239, 0, 0.3827, 0]]]


def test_contacts_at_per_env_mocap_poses_match_mujoco():
    """A mocap box (side b of its sphere-box pair) and a mocap sphere (side a of its sphere-capsule pair), each
    touching a free body, at three per-env mocap poses (tilted, turned, shifted): every contact's point, normal and
    distance is MuJoCo's at the same poses, to round-off."""
    sys = torchsim.load_mjcf(PAIRS, dtype=F64)
    assert sys.contact_mocap and sorted(g.kind for g in sys.contact_groups) == ["sphere_box", "sphere_capsule"]
    m = mujoco.MjModel.from_xml_string(PAIRS)
    d = mujoco.MjData(m)
    batch = len(MOCAP_POS)
    posed = sys.replace(mocap_pos=torch.tensor(MOCAP_POS, dtype=F64), mocap_quat=torch.tensor(MOCAP_QUAT, dtype=F64))
    state = torchsim.init(posed, torch.as_tensor(m.qpos0).expand(batch, -1), torch.zeros(batch, sys.nv, dtype=F64))
    con = contacts(posed, with_world(*(lanes.to_lanes(x, 1) for x in state[:4])))
    # each group's one pair has one point; its geom b, whose side MuJoCo's normal (geom1 -> geom2) is read from
    geom_b = [int(g.geom_b[0]) for g in posed.contact_groups]
    for env in range(batch):
        d.mocap_pos[:] = MOCAP_POS[env]
        d.mocap_quat[:] = MOCAP_QUAT[env]
        mujoco.mj_forward(m, d)
        assert d.ncon == 2
        for c in d.contact[:d.ncon]:
            k = next(i for i, g in enumerate(geom_b) if g in c.geom)
            normal = c.frame[:3] * (1 if c.geom[0] == geom_b[k] else -1)  # ours points from geom b to geom a
            assert c.dist < -1e-3  # overlapping, so the poses matter
            np.testing.assert_allclose(-con.depth[k, env].item(), c.dist, atol=ROUNDOFF)
            np.testing.assert_allclose(con.normal[:, k, env].numpy(), normal, atol=ROUNDOFF)
            np.testing.assert_allclose(con.pos[:, k, env].numpy(), c.pos, atol=ROUNDOFF)
    world = sys.body_mass.shape[0]  # the mocap sides (the wall, b; the ball, a) are the world's: no impulse
    assert con.body_b[0] == world and con.body_a[1] == world and con.body_a[0] != world != con.body_b[1]


def platform_and_cube(timestep):
    """A 1 kg cube resting on a mocap platform turned 30 degrees about z."""
    return f"""<mujoco><option timestep="{timestep}"/><worldbody>
      <body name="platform" mocap="true" pos="0 0 0.5" euler="0 0 30"><geom type="box" size="0.4 0.4 0.05"/></body>
      <body name="cube" pos="0 0 0.65"><freejoint/><geom type="box" size="0.1 0.1 0.1" mass="1"/></body>
      </worldbody></mujoco>"""


def paddle_and_cube(timestep):
    """A 1 kg cube on the floor (friction 1) and a mocap ball 5 mm behind it at its mid height: one contact point
    in MuJoCo as in torchsim (sphere-box is exact; a box paddle's face on the cube's face would touch at no corner,
    which box-box contacts test, and a rod's contacts differ in number)."""
    return f"""<mujoco><option timestep="{timestep}"/><worldbody>
      <geom type="plane" size="2 2 0.1"/>
      <body name="paddle" mocap="true" pos="-0.155 0 0.1"><geom type="sphere" size="0.05"/></body>
      <body name="cube" pos="0 0 0.1"><freejoint/><geom type="box" size="0.1 0.1 0.1" mass="1"/></body>
      </worldbody></mujoco>"""


def mocap_rollout(xml, path, duration, step=0.01, mj_dt=0.002, **options):
    """The cube's position ``(n, 3)`` every ``step`` seconds, the mocap body set to ``path(t)`` at the start of each
    step, in MuJoCo (substeps of ``mj_dt``) and in torchsim (``options``: ``load_mjcf``'s)."""
    m = mujoco.MjModel.from_xml_string(xml(mj_dt))
    d = mujoco.MjData(m)
    sys = torchsim.load_mjcf(xml(step), dtype=F64, **options)
    state = torchsim.init(sys, torch.as_tensor(m.qpos0[None]), torch.zeros(1, sys.nv, dtype=F64))
    ctrl = torch.zeros(1, 0, dtype=F64)
    mj, ours = [], []
    for i in range(int(round(duration / step))):
        target = path((i + 1) * step)
        d.mocap_pos[0] = target
        for _ in range(int(round(step / mj_dt))):
            mujoco.mj_step(m, d)
        state = torchsim.step(sys.replace(mocap_pos=torch.as_tensor(target[None, None])), state, ctrl)
        mj.append(d.qpos[:3].copy())
        ours.append(state.q[0, :3].numpy().copy())
    assert not state.diverged.any()
    return np.array(mj), np.array(ours)


RISE = 0.2  # [m/s]


def rising(t):
    return np.array([0.1 * t, 0.0, 0.5 + RISE * t])  # rising and drifting: the cube is carried up, not along


def test_cube_rides_a_rising_mocap_platform():
    """The platform rises at 0.2 m/s (and drifts 0.1 m/s sideways: at rest in MuJoCo's terms, it drags nothing).
    Soft contacts: the cube follows MuJoCo's height within 0.5 mm over 0.6 s (they differ by 0.2 mm; MuJoCo at 2 ms
    against 0.5 ms by 0.03 mm, but its platform moves in 10 ms jumps in both). Impulse contacts: the cube rises at
    the platform's speed, ``0.2 m/s e contact_timeconst`` = 10.9 mm deep (its separating speed ``depth / (e
    timeconst)`` matches the rise; 10.6 measured), checked to the depth it rests at on a still platform (0.8 mm,
    gravity's share); a platform the contacts did not follow would have left it 0.2 m behind."""
    mj, soft = mocap_rollout(platform_and_cube, rising, 0.6, contact_model="soft")
    print(f"soft: max |z - MuJoCo| {abs(soft - mj)[:, 2].max() * 1e3:.3f} mm")
    np.testing.assert_allclose(soft[:, 2], mj[:, 2], atol=5e-4)
    np.testing.assert_allclose(soft[:, :2], 0.0, atol=1e-6)
    _, impulse = mocap_rollout(platform_and_cube, rising, 0.6)
    _, at_rest = mocap_rollout(platform_and_cube, lambda t: np.array([0.0, 0.0, 0.5]), 0.3)
    rest_depth = 0.65 - at_rest[-1, 2]
    depth = (rising(0.6)[2] + 0.15) - impulse[-1, 2]
    print(f"impulse: depth at rest {rest_depth * 1e3:.2f} mm, rising {depth * 1e3:.2f} mm")
    np.testing.assert_allclose(depth, RISE * np.e * 0.02, atol=rest_depth)
    np.testing.assert_allclose((impulse[-1, 2] - impulse[-11, 2]) / 0.1, RISE, rtol=1e-3)


def floating(xml):
    """``xml`` without the floor and without gravity: only the paddle acts on the cube."""
    return lambda timestep: xml(timestep).replace('<geom type="plane" size="2 2 0.1"/>', "").replace(
        "<option ", '<option gravity="0 0 0" ')


def push(t):
    return np.array([-0.155 + 0.3 * t, 0.0, 0.1])  # 0.3 m/s along x, reaching the cube after 17 ms


def test_mocap_paddle_pushes_a_floating_cube_as_mujoco():
    """Without gravity or floor, the paddle's contact alone moves the cube. Soft contacts are MuJoCo's law on one
    sphere-box point at MuJoCo's substep, so the cube's path is MuJoCo's at 0.5 ms to 1e-6 m (measured 4e-10; MuJoCo
    at 2 ms is 0.3 mm off its own 0.5 ms path). Impulse contacts: the cube ends at the paddle's speed."""
    mj, soft = mocap_rollout(floating(paddle_and_cube), push, 0.5, mj_dt=0.0005, contact_model="soft")
    print(f"soft: cube x after 0.5 s {soft[-1, 0]:.5f} m, MuJoCo {mj[-1, 0]:.5f} m")
    assert mj[-1, 0] > 0.1
    np.testing.assert_allclose(soft, mj, atol=1e-6)
    _, impulse = mocap_rollout(floating(paddle_and_cube), push, 0.5)
    np.testing.assert_allclose((impulse[-1, 0] - impulse[-11, 0]) / 0.1, 0.3, rtol=1e-2)


@pytest.mark.parametrize("contact_model", ["soft", "impulse"])
def test_mocap_paddle_pushes_a_cube_over_the_floor(contact_model):
    """On the floor (friction 9.81 N), the cube's x follows MuJoCo's within 8 mm over 0.5 s (it moves 136 mm): the
    floor's friction is a Coulomb-capped impulse in both contact models where MuJoCo's is soft, which puts the
    cube 6 mm behind (MuJoCo's own 2 ms against 0.5 ms: 0.6 mm); the paddle's contact alone is MuJoCo's (above)."""
    mj, ours = mocap_rollout(paddle_and_cube, push, 0.5, contact_model=contact_model)
    print(f"{contact_model}: cube x after 0.5 s {ours[-1, 0]:.4f} m, MuJoCo {mj[-1, 0]:.4f} m; "
          f"max |x - MuJoCo| {abs(ours - mj)[:, 0].max() * 1e3:.2f} mm")
    assert mj[-1, 0] > 0.1
    np.testing.assert_allclose(ours[:, 0], mj[:, 0], atol=8e-3)


def test_static_pairs_dropped_and_structure_static():
    """A mocap box sunk into the floor makes no pair with it (neither side moves; MuJoCo collides no such pair
    either), only with the free sphere; a model without colliding mocap geoms reads no mocap pose
    (``contact_mocap`` false)."""
    xml = """<mujoco><worldbody><geom type="plane" size="1 1 0.1"/>
      <body mocap="true" pos="0 0 0.05"><geom type="box" size="0.1 0.1 0.1"/></body>
      <body pos="0.5 0 0.05"><freejoint/><geom type="sphere" size="0.1"/></body></worldbody></mujoco>"""
    sys = torchsim.load_mjcf(xml)
    assert [g.kind for g in sys.contact_groups] == ["sphere_box", "sphere_plane"]  # no box_plane
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    assert d.ncon == 1 and m.geom_bodyid[d.contact[0].geom].tolist() == [0, 2]  # the floor and the sphere
    assert not torchsim.load_mjcf(platform_and_cube(0.01).replace('mocap="true"', "")).contact_mocap


def test_plane_on_mocap_body_refused_by_name():
    xml = """<mujoco><worldbody><body name="m" mocap="true"><geom name="tray" type="plane" size="1 1 0.1"/></body>
      <body pos="0 0 0.2"><freejoint/><geom type="sphere" size="0.1"/></body></worldbody></mujoco>"""
    with pytest.raises(UnsupportedMJCFError, match="plane geom 'tray' .*not on the world body"):
        torchsim.load_mjcf(xml)


def test_dm_control_testing_cartpole_loads():
    """dm_control's testing cartpole, refused before for its mocap geoms' default conaffinity (no pair matches)."""
    sys = torchsim.load_mjcf(cached_third_party("dm_control-*/dm_control/mujoco/testing/assets/cartpole.xml"))
    assert sys.mocap_pos.shape == (2, 3) and not sys.contact_mocap


def test_per_env_mocap_platforms_in_the_step_kernel():
    """Mocap poses read by the contacts are inputs of the step kernel too: three envs' platforms at three heights
    carry their cubes as the reference step does (to 1e-9 m over 20 steps, float64), and moving the platforms reuses
    the kernel."""
    sys = torchsim.load_mjcf(platform_and_cube(0.01), dtype=F64)
    platforms = torch.tensor([[[0.0, 0.0, 0.5]], [[0.0, 0.0, 0.52]], [[0.05, 0.0, 0.48]]], dtype=F64)
    per_env = sys.replace(mocap_pos=platforms, mocap_quat=sys.mocap_quat.expand(3, -1, -1))
    start = torchsim.init(sys, sys.q0.expand(3, -1), torch.zeros(3, sys.nv, dtype=F64))
    stepper, expected, got = kernel_beside_reference(per_env, start)
    assert stepper.strategy == "kernel"
    assert (expected.q[:, 2] - start.q[:, 2]).abs().max() > 1e-2  # the raised and lowered platforms moved them
    assert (got.q - expected.q).abs().max() < 1e-9


def test_gradient_through_a_mocap_contact():
    """The cube's x after 0.1 s of the paddle held 1 cm into it (soft contacts) is differentiable in the paddle's
    mocap position: autograd equals central differences to 1e-6 relative (round-off of a 1e-6 m step), and the
    paddle pushes (d x / d paddle_x > 0)."""
    base = torchsim.load_mjcf(floating(paddle_and_cube)(0.01), dtype=F64, contact_model="soft")

    def cube_x_after(paddle):
        sys = base.replace(mocap_pos=paddle[None, None])
        state = torchsim.init(sys, sys.q0[None], torch.zeros(1, sys.nv, dtype=F64))
        for _ in range(10):
            state = torchsim.step(sys, state, torch.zeros(1, 0, dtype=F64))
        return state.q[0, 0]

    paddle = torch.tensor([-0.14, 0.0, 0.1], dtype=F64, requires_grad=True)
    grad, = torch.autograd.grad(cube_x_after(paddle), paddle)
    with torch.no_grad():
        central = torch.stack([(cube_x_after(paddle + 1e-6 * e) - cube_x_after(paddle - 1e-6 * e)) / 2e-6
                               for e in torch.eye(3, dtype=F64)])
    assert grad[0] > 0.1
    torch.testing.assert_close(grad, central, rtol=1e-6, atol=1e-8)


def test_per_env_mocap_platforms_in_the_cuda_kernel(monkeypatch, tmp_path):
    """The same step emitted as CUDA C (one thread an env) and compiled for the host, as tests/test_strategies.py
    checks the GPU kernel: three envs on three platforms step as the reference does (1e-9 m over 20 steps)."""
    monkeypatch.setenv("TORCHSIM_CACHE_DIR", str(tmp_path))
    sys = torchsim.load_mjcf(platform_and_cube(0.01), dtype=F64)
    platforms = torch.tensor([[[0.0, 0.0, 0.5]], [[0.0, 0.0, 0.52]], [[0.05, 0.0, 0.48]]], dtype=F64)
    per_env = sys.replace(mocap_pos=platforms, mocap_quat=sys.mocap_quat.expand(3, -1, -1))
    kernel = StepKernel(per_env, emitter=emit_cuda)
    start = torchsim.init(sys, sys.q0.expand(3, -1), torch.zeros(3, sys.nv, dtype=F64))
    ctrl = torch.zeros(3, 0, dtype=F64)
    expected, got = start, start
    for _ in range(20):
        expected, got = torchsim.step(per_env, expected, ctrl), kernel(per_env, got, ctrl)
    assert (expected.q[:, 2] - start.q[:, 2]).abs().max() > 1e-2
    assert (got.q - expected.q).abs().max() < 1e-9
