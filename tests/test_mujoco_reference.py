"""Physics against MuJoCo on the same MJCF and against closed forms: pendulum period, triple-pendulum trajectory,
a box resting and sliding on a plane, and the ant standing under gravity."""

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from models import ANT, F64, METHODS, PENDULUM

TRIPLE = """
<mujoco><option timestep="0.001"/><worldbody>
  <body pos="0 0 1"><joint type="hinge" axis="0 1 0"/><geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.05"/>
    <body pos="0 0 -0.5"><joint type="hinge" axis="0 1 0"/><geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.05"/>
      <body pos="0 0 -0.5"><joint type="hinge" axis="1 0 0"/><geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.05"/>
      </body></body></body></worldbody></mujoco>"""

BOX = """
<mujoco><option timestep="0.002"/><worldbody><geom type="plane" size="10 10 1" friction="{mu}"/>
  <body pos="0 0 {z}"><freejoint/><geom type="box" size="0.2 0.2 0.05" friction="{mu}" mass="1"/></body>
</worldbody></mujoco>"""


def _zero_ctrl(sys, batch=1):
    return torch.zeros(batch, sys.nu, dtype=F64)


def _period(angles: np.ndarray, dt: float) -> float:
    """Mean period from linearly interpolated zero crossings."""
    idx = np.where(np.diff(np.sign(angles)) != 0)[0]
    crossings = (idx + angles[idx] / (angles[idx] - angles[idx + 1])) * dt
    return 2.0 * float(np.mean(np.diff(crossings)))


@pytest.mark.parametrize("method", METHODS)
def test_pendulum_period_matches_mujoco(method):
    """Item 2: period within 0.5% of MuJoCo's at timestep 1 ms, from 1 rad (a non-linear swing)."""
    m = mujoco.MjModel.from_xml_string(PENDULUM)
    d = mujoco.MjData(m)
    d.qpos[0] = 1.0
    steps = 1800  # > 1 period (1.42 s): three zero crossings
    ref = []
    for _ in range(steps):
        mujoco.mj_step(m, d)
        ref.append(d.qpos[0])
    sys = torchsim.load_mjcf(PENDULUM, method=method, dtype=F64)
    state = torchsim.init(sys, torch.tensor([[1.0]], dtype=F64), torch.zeros(1, 1, dtype=F64))
    ours = []
    for _ in range(steps):
        state = torchsim.step(sys, state, _zero_ctrl(sys))
        ours.append(state.q[0, 0].item())
    rel = _period(np.array(ours), m.opt.timestep) / _period(np.array(ref), m.opt.timestep) - 1
    print(f"{method}: period error vs MuJoCo {rel:+.2e}")
    assert abs(rel) < 5e-3


# Measured max |q - q_mujoco| over 1 s with the default 2 substeps of 0.5 ms: spring 0.012 rad (0.0052 with 4
# substeps); xpbd: see the printed value (its first-order projection damps and shortens the swing: 0.025 rad with
# 1 substep). For scale, MuJoCo at 1 ms vs MuJoCo at 0.1 ms differs by 0.0031 rad on this chain.
TRIPLE_BOUND = {"xpbd": 0.03, "spring": 0.015}


@pytest.mark.parametrize("method", METHODS)
def test_triple_pendulum_follows_mujoco(method):
    """Item 6: a triple pendulum (two pitch hinges, one roll hinge: 3-D motion) tracks MuJoCo's q over 1 s, and
    joint anchors stay together (< 1 mm)."""
    m = mujoco.MjModel.from_xml_string(TRIPLE)
    d = mujoco.MjData(m)
    q0 = np.array([0.8, -0.4, 0.6])
    d.qpos[:] = q0
    sys = torchsim.load_mjcf(TRIPLE, method=method, dtype=F64)
    state = torchsim.init(sys, torch.tensor(q0)[None], torch.zeros(1, 3, dtype=F64))
    err, gap = 0.0, 0.0
    for _ in range(1000):
        state = torchsim.step(sys, state, _zero_ctrl(sys))
        mujoco.mj_step(m, d)
        err = max(err, float(np.abs(state.q[0].numpy() - d.qpos).max()))
        gap = max(gap, float(torchsim.kinematics.anchor_gap(sys, state).max()))
    print(f"{method}: max |q - q_mujoco| {err:.2e} rad, max anchor gap {gap:.2e} m")
    assert err < TRIPLE_BOUND[method]
    assert gap < 1e-3


@pytest.mark.parametrize("method", METHODS)
def test_box_comes_to_rest_at_its_height(method):
    """Item 4a: a box (half height 5 cm) dropped from 45 cm above its resting height rests at z = 0.05 within 2 mm,
    with speed < 1e-3 m/s after 2 s."""
    sys = torchsim.load_mjcf(BOX.format(mu=0.5, z=0.5), method=method, dtype=F64)
    state = torchsim.init(sys, sys.q0[None].clone(), torch.zeros(1, 6, dtype=F64))
    for _ in range(1000):
        state = torchsim.step(sys, state, _zero_ctrl(sys))
    print(f"{method}: rest height {state.x_pos[0, 0, 2].item():.5f}, speed {state.xd_vel.norm().item():.1e}")
    assert abs(state.x_pos[0, 0, 2].item() - 0.05) < 2e-3
    assert state.xd_vel.norm().item() < 1e-3 and state.xd_ang.norm().item() < 1e-3


@pytest.mark.parametrize("method", METHODS)
def test_sliding_box_stops_at_coulomb_distance(method):
    """Item 4b: a box sliding at v0 = 2 m/s with mu = 0.5 stops within 5% of v0^2 / (2 mu g)."""
    v0, mu, g = 2.0, 0.5, 9.81
    sys = torchsim.load_mjcf(BOX.format(mu=mu, z=0.05), method=method, dtype=F64)
    qd = torch.zeros(1, 6, dtype=F64)
    qd[0, 0] = v0
    state = torchsim.init(sys, sys.q0[None].clone(), qd)
    for _ in range(400):  # 0.8 s > stopping time v0 / (mu g) = 0.41 s
        state = torchsim.step(sys, state, _zero_ctrl(sys))
    expected = v0**2 / (2 * mu * g)
    travel = state.x_pos[0, 0, 0].item()
    print(f"{method}: slid {travel:.4f} m, Coulomb {expected:.4f} m")
    assert abs(travel / expected - 1) < 0.05
    assert abs(state.xd_vel[0, 0, 0].item()) < 1e-3



SPHERE = """
<mujoco><option timestep="0.002"/><worldbody><geom type="plane" size="5 5 .1"/>
  <body pos="0 0 0.1"><freejoint/><geom type="sphere" size="0.1" mass="1"/></body></worldbody></mujoco>"""


@pytest.mark.parametrize("depth", [0.02, 0.1])
def test_penetration_pushed_out_at_mujocos_speed(depth):
    """A sphere released ``depth`` deep in the floor leaves it with MuJoCo's peak speed, ``depth / (e tau)`` for its
    critically damped contact (tau = 0.02 s), within 10%: the spring method's Baumgarte speed, not a launch (at
    ``depth / tau`` the 10 cm case flew 1.2 m high, MuJoCo's 0.1 m). Measured: 0.358 vs 0.371 m/s, 1.825 vs 1.871."""
    m = mujoco.MjModel.from_xml_string(SPHERE)
    d = mujoco.MjData(m)
    d.qpos[2] = 0.1 - depth
    sys = torchsim.load_mjcf(SPHERE, method="spring", dtype=F64)
    q = torch.tensor(d.qpos.copy())[None]
    state = torchsim.init(sys, q, torch.zeros(1, 6, dtype=F64))
    peak_mj = peak = 0.0
    for _ in range(100):  # 0.2 s: the speed peaks at tau
        mujoco.mj_step(m, d)
        state = torchsim.step(sys, state, _zero_ctrl(sys))
        peak_mj, peak = max(peak_mj, d.qvel[2]), max(peak, state.qd[0, 2].item())
    print(f"depth {depth}: peak speed {peak:.3f} m/s, MuJoCo {peak_mj:.3f}, depth / (e tau) {depth / (np.e * 0.02):.3f}")
    assert abs(peak / peak_mj - 1) < 0.1


# Measured torso-height difference to MuJoCo after 2 s (home pose, zero control, MuJoCo 4.0 at 10 ms):
# spring -2.0 mm (-1.9 with the old stiff limits) with its default 20 substeps (with stiffness 0.1: -18 mm at 10
# substeps, -2.9 mm at 20, +3.4 mm at 40: the settling rate depends on how contact impulses meet the 1 kg m^2
# armature of 0.04 kg legs, see joint_space.armature_loaded_inertia). xpbd: -28.5 mm, the ankles fold too fast:
# the projection moves the light legs with their bare inertia and armature only gets its share afterwards, at
# velocity level (methods/xpbd.py).
# Item 10: xpbd fails item 7. Spring with soft contacts (the Ant env's default): -2.4 mm (MuJoCo at 0.5 ms, its
# converged answer to 4e-5 m, is within 0.04 mm of its 10 ms answer).
ANT_SETTLE_MM = 3.0


@pytest.mark.parametrize("method, contact_model", [
    ("spring", "impulse"),
    ("spring", "soft"),
    pytest.param("xpbd", "impulse",
                 marks=pytest.mark.xfail(strict=True, reason="settles 28.5 mm low: ankles fold too fast (see above)")),
])
def test_ant_settles_at_mujoco_height(method, contact_model):
    """Item 7: the ant standing from its home pose with zero control is within 3 mm of MuJoCo's torso height
    after 2 s."""
    m = mujoco.MjModel.from_xml_path(str(ANT))
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, 0)
    home = d.qpos.copy()
    for _ in range(200):
        mujoco.mj_step(m, d)
    sys = torchsim.load_mjcf(str(ANT), method=method, contact_model=contact_model, dtype=F64)
    state = torchsim.init(sys, torch.tensor(home)[None], torch.zeros(1, sys.nv, dtype=F64))
    for _ in range(200):
        state = torchsim.step(sys, state, _zero_ctrl(sys))
    diff_mm = 1000 * (state.q[0, 2].item() - d.qpos[2])
    print(f"{method}, {contact_model}: torso height {state.q[0, 2].item():.4f} vs MuJoCo {d.qpos[2]:.4f} ({diff_mm:+.1f} mm)")
    assert abs(diff_mm) < ANT_SETTLE_MM
