"""The spring method's load-time substeps rule (``torchsim.io_mjcf.spring_stability.stiff_enough``): a spring joint
sags under the weight it carries by ``h^2 / kappa`` times the load over its gain, and an arm fixed to the world whose
light link carries heavy ones (robosuite's iiwa and spot_arm) sagged enough at the default 0.5 ms substeps to miss
MuJoCo. The loader raises the default substeps until every joint's gravity sag is within ``SAG_LIMIT``.

The scene: a three-hinge arm hanging from the world, a 0.1 kg wrist (1e-4 kg m^2) between a 2 kg upper arm and a
2 kg hand, off-axis hinges so that the hand's weight loads the wrist's rotational constraints.
"""

import time
import warnings
from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from models import F64
from torchsim.io_mjcf import spring_stability

ARM = """
<mujoco>
  <option timestep="0.002"/>
  <worldbody>
    <body name="upper" pos="0 0 1">
      <joint name="shoulder" axis="0 1 0" damping="0.05"/>
      <inertial pos="0 0 -0.15" mass="2" diaginertia="0.01 0.01 0.003"/>
      <body name="wrist" pos="0 0 -0.3">
        <joint name="twist" axis="1 0 0" damping="0.05"/>
        <inertial pos="0 0 -0.02" mass="0.1" diaginertia="1e-4 1e-4 7e-5"/>
        <body name="hand" pos="0 0 -0.05">
          <joint name="flex" axis="0 1 0" damping="0.05"/>
          <inertial pos="0.1 0.05 -0.1" mass="2" diaginertia="0.01 0.01 0.005"/>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>"""
STEPS = 100  # 0.2 s from rest: the hand's offset COM swings the arm (~9 s for the test at the raised substeps)


def _load(xml, **options):
    """The System (float64) and the loader's warnings."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sys = torchsim.load_mjcf(xml, dtype=F64, **options)
    return sys, [str(w.message) for w in caught]


def _errors(xml, sys, steps):
    """RMS over time and coordinates of torchsim's q and of MuJoCo's at dt against MuJoCo at dt / 4 (the model
    checks' errors, ``studies/check_third_party.py``), from rest at ``qpos0``."""
    runs = {}
    for factor in (1, 4):
        m = mujoco.MjModel.from_xml_string(xml)
        m.opt.timestep /= factor
        d = mujoco.MjData(m)
        runs[factor] = []
        for _ in range(steps):
            mujoco.mj_step(m, d, nstep=factor)
            runs[factor].append(d.qpos.copy())
    state = torchsim.init(sys, sys.q0.reshape(1, -1), torch.zeros(1, sys.nv, dtype=F64))
    ours = []
    for _ in range(steps):
        state = torchsim.step(sys, state, torch.zeros(1, sys.nu, dtype=F64))
        ours.append(state.q[0].numpy().copy())
    fine = np.array(runs[4])
    return float(np.sqrt(np.mean((np.array(ours) - fine) ** 2))), float(np.sqrt(np.mean((np.array(runs[1]) - fine) ** 2)))


def test_sag_goes_as_substep_squared_over_stiffness():
    """The sag is quasi-static: ``h^2 / kappa`` times the load over the gain (4x less at twice the substeps, 2x more
    at half the stiffness), and at the default 0.5 ms substeps the wrist's sag is 90x the limit. (The planar arm
    below, at 4 substeps, missed MuJoCo by 4.6x its dt sensitivity; at the rule's 86 substeps 0.32x.)"""
    sys, _ = _load(ARM, substeps=4)
    sag, joint = spring_stability.gravity_sag(sys)
    assert sys.body_names[int(sys.jnt_child[joint])] in ("wrist", "hand")
    assert sag > 50 * spring_stability.SAG_LIMIT
    assert spring_stability.gravity_sag(sys.replace(substeps=8))[0] == pytest.approx(sag / 4, rel=1e-9)
    assert spring_stability.gravity_sag(sys.replace(joint_stiffness=0.1))[0] == pytest.approx(2 * sag, rel=1e-9)
    # a planar arm (every hinge along y) sags in its plane's normal under a weight in the plane, and counts none
    # under a weight along its axes (a reacher's: the sag is out of the plane the arm moves in)
    planar = ARM.replace('name="twist" axis="1 0 0"', 'name="twist" axis="0 1 0"')
    assert spring_stability.gravity_sag(_load(planar, substeps=4)[0])[0] > 50 * spring_stability.SAG_LIMIT
    across = planar.replace('<option timestep="0.002"/>', '<option timestep="0.002" gravity="0 -9.81 0"/>')
    assert spring_stability.gravity_sag(_load(across, substeps=4)[0]) == (0.0, -1)


def test_given_default_substeps_the_arm_misses_mujoco():
    """The cause, pinned: at 0.5 ms substeps given explicitly the loader keeps them, without a warning, and the
    passive rollout misses the model checks' contact-free bar, 2x MuJoCo's own timestep sensitivity (measured:
    2.7x)."""
    sys, caught = _load(ARM, substeps=4)
    assert sys.substeps == 4
    assert not any("substeps" in w for w in caught), caught
    ours, mujoco_dt = _errors(ARM, sys, STEPS)
    assert ours > 2.0 * mujoco_dt


def test_default_substeps_are_raised_until_the_arm_tracks_mujoco():
    """At the default the loader raises the substeps (one warning naming them) so that the sag is within the limit,
    and the rollout then tracks MuJoCo within 2x its own timestep sensitivity (measured: 0.32x at 38 substeps)."""
    sys, caught = _load(ARM)
    assert sys.substeps > 4
    assert spring_stability.gravity_sag(sys)[0] <= spring_stability.SAG_LIMIT
    assert spring_stability.gravity_sag(sys.replace(substeps=sys.substeps - 1))[0] > spring_stability.SAG_LIMIT
    assert sum(f"substeps 4 -> {sys.substeps}" in w for w in caught) == 1, caught
    ours, mujoco_dt = _errors(ARM, sys, STEPS)
    assert ours <= 2.0 * mujoco_dt


ENV_ASSETS = Path(__file__).resolve().parent.parent / "envs" / "assets"


@pytest.mark.parametrize("name", sorted(p.stem for p in ENV_ASSETS.glob("*.xml")))
def test_env_models_keep_their_substeps(name):
    """The envs' models are floating bases, fixed-base arms in zero gravity or pendulums on slides: their joints
    carry at most 2e-7 rad of sag (the inverted pendulum's pole, 1.8e-7), so their default substeps stay as they
    were, without a warning, and the rule costs little at load (< 0.1 s)."""
    path = ENV_ASSETS / f"{name}.xml"
    m = mujoco.MjModel.from_xml_path(str(path))
    sys, caught = _load(str(path))
    assert sys.substeps == max(1, int(np.ceil(m.opt.timestep / 5e-4 - 1e-9)))
    assert not any("substeps" in w for w in caught), caught
    start = time.perf_counter()
    assert spring_stability.gravity_sag(sys)[0] <= spring_stability.SAG_LIMIT / 100
    assert time.perf_counter() - start < 0.1
