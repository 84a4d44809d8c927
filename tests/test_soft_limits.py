"""Soft joint limits (``joint_space.limit_rows``) against MuJoCo (float64, CPU): MuJoCo's ``solref``/``solimp``
constraint, so a violated limit is released at MuJoCo's speed and a loaded limit gives way as far as MuJoCo's.

The hinge is the humanoid's knee in miniature: a 2 kg shin capsule and a 1 kg foot ball hanging from a hinge about
-y with range [-160, -2] degrees and armature 0.006, started at 0 (2 degrees past the upper side). At the default
``solref`` (0.02 s, damping ratio 1) and ``solimp`` (impedance 0.95 this deep) MuJoCo's limit accelerates it as the
critically damped ``a = -imp (B v + K imp r)`` (``B = 105 /s``, ``K = 2770 /s^2``): 0.39 rad/s after 6 ms, and the
limit lets go at 0.64 rad/s, once the damper would have to pull. The old stiff limits kicked it to 6.3 rad/s
(spring) and 36 rad/s (XPBD) in 6 ms.
"""

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from models import F64

MJ_DT = 1e-4  # MuJoCo's reference step: its release rates are within 0.2% of its own at 0.02 ms
STEP = 0.002  # torchsim's step, 4 substeps of 0.5 ms (the engine's default substep)


def knee(gravity="0 0 0", solref="0.02 1", solimp="0.9 0.95 0.001 0.5 2", margin=0.0):
    return f"""<mujoco><option timestep="{STEP}" gravity="{gravity}"/><worldbody><body pos="0 0 1">
      <joint type="hinge" axis="0 -1 0" range="-160 -2" armature="0.006" solreflimit="{solref}"
             solimplimit="{solimp}" margin="{margin}"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.049" mass="2" contype="0" conaffinity="0"/>
      <geom type="sphere" pos="0 0 -0.35" size="0.075" mass="1" contype="0" conaffinity="0"/>
    </body></worldbody></mujoco>"""


def loaded_pendulum(solref="0.02 1"):
    """The frictionloss tests' pendulum (gravity torque 7.36 N m at the horizontal, inertia 0.344 kg m^2) on a
    hinge about y whose upper limit is the horizontal: gravity holds it on the limit."""
    return f"""<mujoco><option timestep="{STEP}"/><worldbody><body pos="0 0 1">
      <joint type="hinge" axis="0 1 0" range="-90 0" solreflimit="{solref}"/>
      <geom type="capsule" fromto="0 0 0 0.5 0 0" size="0.05" mass="1" contype="0" conaffinity="0"/>
      <geom type="sphere" pos="0.5 0 0" size="0.1" mass="1" contype="0" conaffinity="0"/>
    </body></worldbody></mujoco>"""


def slider(gravity="0 0 -9.81"):
    """A 2 kg box on a vertical slide with range [0, 0.5] m, armature 0.5 kg."""
    return f"""<mujoco><option timestep="{STEP}" gravity="{gravity}"/><worldbody><body pos="0 0 1">
      <joint type="slide" axis="0 0 1" range="0 0.5" armature="0.5"/>
      <geom type="box" size="0.1 0.1 0.1" mass="2" contype="0" conaffinity="0"/>
    </body></worldbody></mujoco>"""


def mujoco_run(xml, q0, duration):
    """MuJoCo's ``qpos[0]``, ``qvel[0]`` after every ``STEP``, stepping at ``MJ_DT`` from rest at ``q0``."""
    m = mujoco.MjModel.from_xml_string(xml)
    m.opt.timestep = MJ_DT  # the limit's gains were fixed at load, from the model's own timestep (refsafe)
    d = mujoco.MjData(m)
    d.qpos[0] = q0
    q, qd = [], []
    for _ in range(round(duration / STEP)):
        for _ in range(round(STEP / MJ_DT)):
            mujoco.mj_step(m, d)
        q.append(d.qpos[0])
        qd.append(d.qvel[0])
    return np.array(q), np.array(qd)


def torchsim_run(xml, q0, duration, method):
    sys = torchsim.load_mjcf(xml, method=method, dtype=F64, substeps=4)
    state = torchsim.init(sys, torch.full((1, 1), q0, dtype=F64), torch.zeros(1, 1, dtype=F64))
    ctrl = torch.zeros(1, 0, dtype=F64)
    q, qd = [], []
    for _ in range(round(duration / STEP)):
        state = torchsim.step(sys, state, ctrl)
        q.append(state.q[0, 0].item())
        qd.append(state.qd[0, 0].item())
    assert not state.diverged.any()
    return np.array(q), np.array(qd)


@pytest.mark.parametrize("method, params", [
    ("spring", {}), ("xpbd", {}),
    # a wide, steep impedance curve and a margin: the limit acts 0.6 degrees early, its impedance falls as it lets go
    ("spring", dict(solimp="0.8 0.99 0.05 0.3 3", margin=0.01, solref="0.03 0.7")),
])
def test_violated_limit_releases_at_mujoco_speed(method, params):
    """Gravity off, 2 degrees past the limit: the rate after 6 ms, and its course over 50 ms (the release at 0.64
    rad/s), within 5% of MuJoCo's top speed (MuJoCo at our 0.5 ms substep differs from its 0.02 ms run by 1.1%); the
    angle within 5% of MuJoCo's travel. A limit 10% stiffer (solref 0.018 s) misses them by 21%, 15% and 14%, the
    old stiff limits by 10-90x (6.3 and 36 rad/s after 6 ms on the humanoid's knee)."""
    mj_q, mj_qd = mujoco_run(knee(**params), 0.0, 0.05)
    q, qd = torchsim_run(knee(**params), 0.0, 0.05, method)
    print(f"{method}: rate at 6 ms {qd[2]:.4f} (MuJoCo {mj_qd[2]:.4f}), at 50 ms {qd[-1]:.4f} ({mj_qd[-1]:.4f}) "
          f"rad/s; max rate error {abs(qd - mj_qd).max():.4f} rad/s, angle {abs(q - mj_q).max():.2e} rad")
    top = abs(mj_qd).max()
    assert abs(qd[2] - mj_qd[2]) < 0.05 * abs(mj_qd[2])
    assert abs(qd - mj_qd).max() < 0.05 * top
    assert abs(q - mj_q).max() < 0.05 * abs(mj_q).max()


@pytest.mark.parametrize("method", ["spring", "xpbd"])
def test_loaded_limit_gives_way_as_far_as_mujocos(method):
    """Gravity holds the pendulum on its limit: MuJoCo's limit settles where ``imp aref + (1 - imp) a0 = 0``, here
    0.59 mrad past it (imp 0.93 on solimp's curve). The depth does not depend on the step, so it must match within
    3% over the last 0.1 s (measured: to 4 digits): a time constant 10% longer settles 11% deeper, half of it 2.6x
    shallower. The old limits missed it far: XPBD's projection held it at 0; the spring method's stiff spring
    (``0.2 / (h^2 w)``, ``w`` ~ 16 /(kg m^2) about the link's COM) would hold it ~0.15 mrad deep, and the tendons'
    explicit soft force (no ``a0``) would sink it ``1 / (1 - imp)`` = 15x deeper."""
    mj_q, _ = mujoco_run(loaded_pendulum(), 0.0, 0.3)
    q, _ = torchsim_run(loaded_pendulum(), 0.0, 0.3, method)
    depth, mj_depth = q[-50:], mj_q[-50:]
    print(f"{method}: depth past the limit {depth.mean() * 1e3:.4f} mrad (MuJoCo {mj_depth.mean() * 1e3:.4f}), "
          f"spread {np.ptp(depth) * 1e3:.2e} mrad")
    assert 0.0 < mj_depth.mean() and np.ptp(mj_depth) < 0.01 * mj_depth.mean()  # MuJoCo at rest on the limit
    assert abs(depth - mj_depth.mean()).max() < 0.03 * mj_depth.mean()


@pytest.mark.parametrize("method", ["spring", "xpbd"])
def test_slide_limit_releases_and_holds_as_mujocos(method):
    """The box on a vertical slide: started 2 cm below its range with gravity off it is released as MuJoCo's (rate
    within 5% of MuJoCo's top speed over 50 ms); under gravity it rests on the limit as deep as MuJoCo's (3%, as the
    hinge's)."""
    mj_q, mj_qd = mujoco_run(slider(gravity="0 0 0"), -0.02, 0.05)
    q, qd = torchsim_run(slider(gravity="0 0 0"), -0.02, 0.05, method)
    print(f"{method}: rate at 6 ms {qd[2]:.4f} (MuJoCo {mj_qd[2]:.4f}), at 50 ms {qd[-1]:.4f} ({mj_qd[-1]:.4f}) m/s")
    assert abs(qd - mj_qd).max() < 0.05 * abs(mj_qd).max()
    mj_q, _ = mujoco_run(slider(), 0.0, 0.3)
    q, _ = torchsim_run(slider(), 0.0, 0.3, method)
    print(f"{method}: depth under its weight {-q[-50:].mean() * 1e3:.4f} mm (MuJoCo {-mj_q[-50:].mean() * 1e3:.4f})")
    assert abs(q[-50:] - mj_q[-50:].mean()).max() < 0.03 * abs(mj_q[-50:].mean())


def camera_on_kicker():
    """dm_control's boxhead in miniature: a 20 kg head on a damped vertical hinge carries a 1 kg camera on a pitch
    hinge with range [-0.35, 0] degrees, started on its upper end, and a kick slide (damping 100 N s/m) whose light
    arms sit 1.5 cm off the slide's line and carry an 18 kg ball on a roll hinge, falling under gravity."""
    return f"""<mujoco><option timestep="{STEP}"/><worldbody><body pos="0 0 1">
      <joint type="hinge" axis="0 0 1" damping="4"/>
      <geom type="box" size="0.2 0.2 0.1" mass="20" contype="0" conaffinity="0"/>
      <body pos="0 0 0.4">
        <inertial pos="0 0 0" mass="1" diaginertia="1 1 1"/>
        <joint type="hinge" axis="0 1 0" range="-0.35 0"/>
      </body>
      <body>
        <joint type="slide" axis="0 0 -1" range="0 0.4" damping="100"/>
        <geom type="capsule" fromto="0 0.35 -0.7 0.03 0.8 -0.7" size="0.1" density="10" contype="0" conaffinity="0"/>
        <geom type="capsule" fromto="0 -0.35 -0.7 0.03 -0.8 -0.7" size="0.1" density="10" contype="0" conaffinity="0"/>
        <body pos="0 0 -0.7">
          <joint type="hinge" axis="1 0 0" damping="2"/>
          <geom type="sphere" size="0.35" density="100" contype="0" conaffinity="0"/>
        </body>
      </body>
    </body></worldbody></mujoco>"""


def test_hinge_limit_reads_rates_after_a_slide_turned_its_parent():
    """The camera, sent 0.064 rad/s into its limit, is pushed back out by MuJoCo's limit (1.9 mrad out after 0.3 s)
    while the kick slide falls. The slide's damping impulse acts at its child's COM, off the slide's line, so its
    moment turns the head about the pitch axis every substep: a limit solved on the rates before that impulse held
    the camera ~0.5 mrad inside its limit and was off MuJoCo by 2.8 mrad (148% of MuJoCo's travel). Solved on the
    rates after it, the pitch follows MuJoCo within 10% of its travel (measured 3.6%; MuJoCo at our 0.5 ms substep
    differs from its 0.1 ms run by ~1%)."""
    xml = camera_on_kicker()
    m = mujoco.MjModel.from_xml_string(xml)
    m.opt.timestep = MJ_DT
    d = mujoco.MjData(m)
    qd0 = np.array([0.0, 0.064, 0.0, 0.0])
    d.qvel[:] = qd0
    sys = torchsim.load_mjcf(xml, dtype=F64, substeps=4)
    state = torchsim.init(sys, torch.zeros(1, 4, dtype=F64), torch.tensor(qd0[None]))
    pitch, mj_pitch = [], []
    for _ in range(round(0.3 / STEP)):
        for _ in range(round(STEP / MJ_DT)):
            mujoco.mj_step(m, d)
        state = torchsim.step(sys, state, torch.zeros(1, 0, dtype=F64))
        pitch.append(state.q[0, 1].item())
        mj_pitch.append(d.qpos[1])
    pitch, mj_pitch = np.array(pitch), np.array(mj_pitch)
    print(f"pitch after 0.3 s {pitch[-1] * 1e3:.4f} mrad (MuJoCo {mj_pitch[-1] * 1e3:.4f}), max error "
          f"{abs(pitch - mj_pitch).max() * 1e3:.4f} mrad")
    assert not state.diverged.any()
    assert mj_pitch[-1] < -1e-3  # MuJoCo pushed the camera out of its limit
    assert abs(pitch - mj_pitch).max() < 0.1 * abs(mj_pitch).max()


def light_link_carrying_a_heavy_one(light_mass):
    """A 0.3 m link of ``light_mass`` kg on a hinge with range [-30, 30] degrees, carrying a 2 kg 0.3 m link on a
    free hinge at its tip: from the horizontal, gravity swings both onto the upper side (0.52 rad, the hinge about +y)."""
    return f"""<mujoco><option timestep="{STEP}"/><worldbody><body pos="0 0 1">
      <joint type="hinge" axis="0 1 0" range="-30 30"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.02" mass="{light_mass}" contype="0" conaffinity="0"/>
      <body pos="0.3 0 0">
        <joint type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="2" contype="0" conaffinity="0"/>
      </body>
    </body></worldbody></mujoco>"""


def rollout_errors(xml, duration, contact_model="impulse"):
    """RMS over ``duration`` and the two angles of torchsim's error (default substeps, ``load_mjcf``'s
    ``contact_model``) and of MuJoCo at ``STEP``, both against MuJoCo at ``STEP / 4``
    (``studies/check_third_party.py``'s verdict quantities)."""
    runs = []
    for factor in (1, 4):
        m = mujoco.MjModel.from_xml_string(xml)
        m.opt.timestep = STEP / factor
        d = mujoco.MjData(m)
        q = []
        for _ in range(round(duration / STEP)):
            for _ in range(factor):
                mujoco.mj_step(m, d)
            q.append(d.qpos.copy())
        runs.append(np.array(q))
    sys = torchsim.load_mjcf(xml, dtype=F64, contact_model=contact_model)
    state = torchsim.init(sys, torch.zeros(1, 2, dtype=F64), torch.zeros(1, 2, dtype=F64))
    q = []
    for _ in range(round(duration / STEP)):
        state = torchsim.step(sys, state, torch.zeros(1, 0, dtype=F64))
        q.append(state.q[0].numpy().copy())
    rms = lambda a: float(np.sqrt(np.mean((a - runs[1]) ** 2)))  # noqa: E731
    return rms(np.array(q)), rms(runs[0])


@pytest.mark.parametrize("light_mass", [
    2.0,
    pytest.param(0.1, marks=pytest.mark.xfail(strict=True, reason=(
        "the limit's impulse acts on the two bodies of its joint (their inverse inertias, joint_space.limit_rows), "
        "MuJoCo's on the articulation (M^-1): a light link stopped alone lets its heavy child stretch the joint "
        "spring between them and bounce back (ratio 13 at 4 substeps, 9.4 at 8, 1.9 at 16, 0.6 at 32); boxhead's "
        "kick slide and spot_arm's shoulder miss by it"))),
])
def test_limit_stops_a_link_carrying_a_heavier_one_as_mujoco(light_mass):
    """The two links swing down onto the first hinge's limit and the second swings on past it: over 0.5 s torchsim
    tracks MuJoCo within twice MuJoCo's own timestep sensitivity (the robot models' verdict), measured 0.36x with a
    2 kg first link."""
    ts, mj = rollout_errors(light_link_carrying_a_heavy_one(light_mass), 0.5)
    print(f"{light_mass} kg link: torchsim {ts:.3e} rad, MuJoCo dt vs dt/4 {mj:.3e} rad, ratio {ts / mj:.2f}")
    assert ts <= 2.0 * mj


def test_articulated_model_stops_a_link_carrying_a_heavier_one_as_mujoco():
    """The articulated model (``contact_model="articulated"``, ``torchsim.tree_solve``): with the limit's impulse
    meeting the rigid articulation (``M^-1``) and the joints held at the velocity level, the 0.1 kg link the
    default misses on (above) tracks MuJoCo within the same bound; measured 0.52x MuJoCo's own timestep
    sensitivity (the default: 13x)."""
    xml = light_link_carrying_a_heavy_one(0.1)
    ts, mj = rollout_errors(xml, 0.5, "articulated")
    print(f"articulated: torchsim {ts:.3e} rad, MuJoCo dt vs dt/4 {mj:.3e} rad, ratio {ts / mj:.2f}")
    assert ts <= 2.0 * mj
