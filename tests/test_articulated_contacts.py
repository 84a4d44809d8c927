"""The articulated model (``load_mjcf(contact_model="articulated")``, ``torchsim.tree_solve``): MuJoCo's Euler step
on the rigid tree, velocities, limits and soft contacts solved through it, against MuJoCo, float64, eager.

A free body alone is its own tree, so there the articulated contacts are the soft ones (the soft tests' scenes,
``tests/test_soft_contacts.py``, rerun here); on a robot the joints are exact and a foot's impulse moves the whole
tree, as MuJoCo's solve does: an actuated walker in the air and the hopper's landing then take MuJoCo's steps.
"""

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from models import F64, REPO, mujoco_rollout, random_q
from test_soft_contacts import mujoco_heights, scene, torchsim_heights

HOPPER = (REPO / "envs" / "assets" / "hopper.xml").read_text()


def test_a_free_body_rests_and_lands_as_with_soft_contacts():
    """A box resting on four corners and a sphere dropped from 0.2 m: the articulated contacts' heights are the soft
    contacts' (a free body's joint-space inertia is its own) to 1e-9 m, and MuJoCo's within 1e-4 m over 0.5 s (the
    soft tests' bound). Also a box of friction 2 under an elliptic cone, whose normal MuJoCo regularises with the
    bare ``R`` where the pyramid's edges would sink it 5.3x deeper (measured 2e-13 m from MuJoCo)."""
    elliptic = scene("box", mu=2.0)[0].replace("<option ", '<option cone="elliptic" ')
    for xml in (scene("box")[0], scene("sphere", z=0.3)[0], elliptic):
        mj, _ = mujoco_heights(xml, 1000)
        ours, soft = torchsim_heights(xml, 1000, "articulated"), torchsim_heights(xml, 1000, "soft")
        print(f"max |articulated - soft| {abs(ours - soft).max():.1e} m, |articulated - MuJoCo| "
              f"{abs(ours - mj).max():.1e} m")
        assert abs(ours - soft).max() < 1e-9
        assert abs(ours - mj).max() < 1e-4


def mujoco_slide(xml_at, qd0, seconds: float, record_dt: float):
    """MuJoCo's horizontal velocity ``(T, 2)`` of the scene ``xml_at(dt)``'s free body started at ``qd0``, every
    ``record_dt`` over ``seconds``, stepped at ``dt``."""
    def run(dt):
        m = mujoco.MjModel.from_xml_string(xml_at(dt))
        d = mujoco.MjData(m)
        d.qvel[:] = qd0
        every, out = round(record_dt / dt), []
        for i in range(round(seconds / dt)):
            mujoco.mj_step(m, d)
            if (i + 1) % every == 0:
                out.append(d.qvel[:2].copy())
        return np.array(out)
    return run


def test_a_sliding_box_stops_as_mujocos_pyramid_stops_it():
    """A box sliding at 1.5 m/s (friction 0.5), along x and along the diagonal: MuJoCo's pyramidal cone holds the
    friction along an edge's axis to ``mu`` times the load but along the diagonal to ``mu / sqrt 2`` of it, so the
    diagonal slide lasts longer (0.50 m/s left at 0.15 s, 0.04 along x; torchsim 0.39 and 0.04). The articulated
    contacts solve the same pyramid: their velocities stay closer to MuJoCo's converged answer (0.1 ms steps) than
    MuJoCo's own at the scene's 2 ms step (measured 0.090 against 0.196 m/s along x, 0.075 against 0.090 on the
    diagonal). The soft model's per-point friction stops every direction alike (0.52 m/s at 0.1 s on the diagonal;
    MuJoCo 0.81)."""
    def xml_at(dt):
        return scene("box", mu=0.5, dt=dt)[0]

    sys = torchsim.load_mjcf(xml_at(0.002), dtype=F64, contact_model="articulated")
    speed_at_150ms = []
    for direction in ((1.0, 0.0), (2 ** -0.5, 2 ** -0.5)):
        qd0 = np.zeros(6)
        qd0[:2] = 1.5 * np.array(direction)
        run = mujoco_slide(xml_at, qd0, 0.3, 0.002)
        converged, mj = run(0.0001), run(0.002)
        state = torchsim.init(sys, sys.q0[None], torch.tensor(qd0[None]))
        ours = []
        for _ in range(len(mj)):
            state = torchsim.step(sys, state, torch.zeros(1, 0, dtype=F64))
            ours.append(state.qd[0, :2].numpy().copy())
        ours = np.array(ours)
        print(f"{direction}: max |v - converged| torchsim {abs(ours - converged).max():.3f}, MuJoCo at 2 ms "
              f"{abs(mj - converged).max():.3f} m/s; speed at 0.15 s {np.linalg.norm(ours[74]):.3f}, converged "
              f"{np.linalg.norm(converged[74]):.3f}")
        assert abs(ours - converged).max() < abs(mj - converged).max()
        speed_at_150ms.append(np.linalg.norm(ours[74]))
    # an isotropic cone would leave both near the 0.04 m/s along x
    assert speed_at_150ms[0] < 0.1 and speed_at_150ms[1] > 0.3


def test_hopper_lands_as_mujoco():
    """The envs' hopper (``envs/assets/hopper.xml``) from its initial pose with random velocities
    (``studies/check_third_party.py``'s start: seed 0, 0.1 std; 0.5 s passive, landing on its foot and tipping):
    the articulated model, one substep per timestep (its default), integrates as MuJoCo does, so its trajectory
    stays on MuJoCo's at the same timestep: RMS within 1 % of MuJoCo's own timestep sensitivity (measured 0.18 %;
    with the joints as springs 0.55x of it, the soft contacts 140x: their impulse stops the foot alone, and the leg
    and torso swing on through the joint springs)."""
    m = mujoco.MjModel.from_xml_string(HOPPER)
    steps = round(0.5 / m.opt.timestep)
    qd0 = np.random.default_rng(0).normal(0.0, 0.1, m.nv)
    at_dt = mujoco_rollout(HOPPER, m.qpos0, qd0, steps)
    mj = np.sqrt(np.mean((at_dt - mujoco_rollout(HOPPER, m.qpos0, qd0, steps, divide=4)) ** 2))
    errors = {}
    for contact_model in ("articulated", "soft"):
        sys = torchsim.load_mjcf(HOPPER, dtype=F64, contact_model=contact_model)
        state = torchsim.init(sys, torch.tensor(m.qpos0[None].copy()), torch.tensor(qd0[None]))
        q = []
        for _ in range(steps):
            state = torchsim.step(sys, state, torch.zeros(1, sys.nu, dtype=F64))
            q.append(state.q[0].numpy().copy())
        errors[contact_model] = np.sqrt(np.mean((np.array(q) - at_dt) ** 2)) / mj
    print(f"RMS distance from MuJoCo at the same timestep over MuJoCo's dt sensitivity: {errors}")
    assert errors["articulated"] < 0.01
    assert errors["soft"] > 20.0  # what the articulated solve is for


def test_the_joints_are_exact_at_mujocos_timestep():
    """The articulated model steps at MuJoCo's timestep (one substep, the loader's default) with its joints exact:
    the Ant under full-range random controls for 2 s (200 steps, 16 envs, float64), its feet kicking the torso about,
    keeps every joint's anchors together to rounding (the positions are put back onto the tree each substep). It has
    no joint springs, so the springs' gains are refused by name."""
    xml = (REPO / "envs" / "assets" / "ant.xml").read_text()
    sys = torchsim.load_mjcf(xml, dtype=F64, contact_model="articulated")
    assert sys.substeps == 1
    rng = np.random.default_rng(0)
    m = mujoco.MjModel.from_xml_string(xml)
    state = torchsim.init(sys, torch.tensor(random_q(m, 16, rng)), torch.tensor(rng.normal(0.0, 0.1, (16, m.nv))))
    largest_gap = 0.0
    for step in range(200):
        if step % 5 == 0:
            ctrl = torch.tensor(rng.uniform(-1.0, 1.0, (16, sys.nu)))
        state = torchsim.step(sys, state, ctrl)
        largest_gap = max(largest_gap, torchsim.kinematics.anchor_gap(sys, state).max().item())
    assert not state.diverged.any()
    assert largest_gap < 1e-12
    with pytest.raises(ValueError, match="joint_stiffness and joint_damping"):
        torchsim.load_mjcf(xml, contact_model="articulated", joint_stiffness=0.5)


def test_the_ants_constrained_steps_are_mujocos():
    """Every state MuJoCo's Ant visits over 1 s from 32 random starts under random controls (3200; 2941 with a joint
    at its limit or a foot on the floor), stepped once by both, float64: the articulated step gives MuJoCo's rates
    to 1e-6 on all but 1 % of the constrained ones (measured: all but 7, median error 1e-10). Two of MuJoCo's rules make
    it so. A capsule's contact frame (and so its friction pyramid) is aligned with the capsule's axis
    (``mjc_PlaneCapsule``), not world y: a foot landing as it slides meets a different pyramid. And the constraint
    solve sees ``M`` with the joint damping's force explicit, the damping implicit only in the final solve
    (``mj_Euler``): a hinge stopped at its limit at 8 rad/s differs by 0.1 rad/s otherwise. Before both, 2660 of
    the 2941 were off by more than 1e-6 (median 1.2e-3, worst 8.0). The few left
    are the pyramid solve's ``PIVOT_PASSES`` (4) ending before its active set settles (worst 18.7; with 6 passes
    none is left)."""
    xml = (REPO / "envs" / "assets" / "ant.xml").read_text()
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    rng = np.random.default_rng(0)
    visited = []  # (qpos, qvel, ctrl, whether a constraint acts)
    for start in random_q(m, 32, rng):
        d.qpos[:], d.qvel[:] = start, rng.normal(0.0, 0.1, m.nv)
        for step in range(100):
            if step % 5 == 0:
                d.ctrl[:] = rng.uniform(-1.0, 1.0, m.nu)
            mujoco.mj_forward(m, d)
            visited.append((d.qpos.copy(), d.qvel.copy(), d.ctrl.copy(), d.nefc > 0))
            mujoco.mj_step(m, d)
    q, qd, ctrl, constrained = (np.array(x) for x in zip(*visited))
    after = []
    for qpos, qvel, u in zip(q, qd, ctrl):
        d.qpos[:], d.qvel[:], d.ctrl[:] = qpos, qvel, u
        mujoco.mj_step(m, d)
        after.append(d.qvel.copy())
    sys = torchsim.load_mjcf(xml, dtype=F64, contact_model="articulated")
    state = torchsim.step(sys, torchsim.init(sys, torch.tensor(q), torch.tensor(qd)), torch.tensor(ctrl))
    error = np.linalg.norm(state.qd.numpy() - np.array(after), axis=1)[constrained]
    print(f"{constrained.sum()} constrained states of {len(q)}: {(error > 1e-6).sum()} off by more than 1e-6, "
          f"median {np.median(error):.1e}, worst {error.max():.2f}")
    assert constrained.sum() > 2500
    assert np.median(error) < 1e-9 and (error > 1e-6).mean() < 0.01


def test_an_upright_capsule_slides_as_mujocos():
    """A capsule standing upright on the floor, sliding at 1.1 m/s: its axis, which MuJoCo turns a capsule's contact
    frame to, is along the normal and gives no tangent, so the pyramid falls back to MuJoCo's frame (world x; the
    same four edges as world y on a level floor) and its friction acts: 0.2 s at 2 ms steps on MuJoCo's path to
    1e-9 (measured 0; with the axis taken as the tangent, the edges were the normal alone and the capsule slid on
    unbraked)."""
    xml = """<mujoco><option timestep="0.002"/><worldbody><geom type="plane" size="5 5 .1"/>
      <body pos="0 0 0.19"><freejoint/><geom type="capsule" fromto="0 0 -0.1 0 0 0.1" size="0.1"/></body>
      </worldbody></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    d.qvel[:2] = 1.0, 0.5
    sys = torchsim.load_mjcf(xml, dtype=F64, contact_model="articulated")
    state = torchsim.init(sys, torch.tensor(d.qpos[None].copy()), torch.tensor(d.qvel[None].copy()))
    for _ in range(100):
        mujoco.mj_step(m, d)
        state = torchsim.step(sys, state, torch.zeros(1, 0, dtype=F64))
    assert np.linalg.norm(d.qvel[:2]) < 1.05  # braked
    np.testing.assert_allclose(state.qd[0].numpy(), d.qvel, atol=1e-9)


def test_actuated_walker_in_the_air_steps_as_mujoco():
    """The envs' walker2d 2 m above its floor, from 32 random states (joints uniform over their range widened by
    0.1 rad, so that some start past a limit; rates N(0, 2); random controls), one env step (4 timesteps), median
    errors of ``qd`` relative to the median change of ``qd``: the articulated model (one substep per timestep)
    takes MuJoCo's step: its median distance from MuJoCo at the same timestep is 2e-12 (asserted under 1e-4 of
    MuJoCo's own error against MuJoCo at a twentieth of the timestep), and its own error against that is MuJoCo's
    within 2 % (measured 0.5 %, from the few states where the two differ). With the joints as springs (the soft
    model, the same without contacts) the error is 3.6x MuJoCo's: the springs pass the actuators' torques on a
    substep or more late."""
    xml = (REPO / "envs" / "assets" / "walker2d.xml").read_text()
    m = mujoco.MjModel.from_xml_string(xml)
    rng = np.random.default_rng(0)
    wide = m.jnt_range.copy()
    m.jnt_range[:] = wide + np.array([-0.1, 0.1])  # sampled past the limits, then stepped with the model's own
    q0 = random_q(m, 32, rng)
    m.jnt_range[:] = wide
    q0[:, 1] += 2.0  # rootz: nothing touches the floor within the step
    qd0, ctrl = rng.normal(0.0, 2.0, (32, m.nv)), rng.uniform(-1.0, 1.0, (32, m.nu))

    def mujoco_step(divide):
        model = mujoco.MjModel.from_xml_string(xml)
        model.opt.timestep /= divide
        d, out = mujoco.MjData(model), []
        for q, qd, u in zip(q0, qd0, ctrl):
            mujoco.mj_resetData(model, d)
            d.qpos[:], d.qvel[:], d.ctrl[:] = q, qd, u
            mujoco.mj_step(model, d, nstep=4 * divide)
            out.append(d.qvel.copy())
        return np.array(out)

    converged, at_dt = mujoco_step(20), mujoco_step(1)
    scale = np.median(np.abs(converged - qd0))
    errors = {"MuJoCo": np.median(np.abs(at_dt - converged)) / scale}
    for contact_model in ("articulated", "soft"):
        sys = torchsim.load_mjcf(xml, dtype=F64, contact_model=contact_model)
        state = torchsim.init(sys, torch.tensor(q0), torch.tensor(qd0))
        for _ in range(4):
            state = torchsim.step(sys, state, torch.tensor(ctrl))
        errors[contact_model] = np.median(np.abs(state.qd.numpy() - converged)) / scale
        if contact_model == "articulated":
            errors["articulated vs MuJoCo at its timestep"] = np.median(np.abs(state.qd.numpy() - at_dt)) / scale
    print(f"median |qd - converged| / median |change of qd|: {errors}")
    assert abs(errors["articulated"] - errors["MuJoCo"]) < 0.02 * errors["MuJoCo"]
    assert errors["articulated vs MuJoCo at its timestep"] < 1e-4 * errors["MuJoCo"]
    assert errors["soft"] > 2.0 * errors["MuJoCo"]  # what holding the joints in the tree's solve is for


def test_refused_where_the_tree_has_no_columns_for_the_joints():
    """Two hinges of one body at different anchors are no rigid pivot: a clear error at load, not a wrong ``M``."""
    xml = """<mujoco><worldbody><body pos="0 0 1">
      <joint type="hinge" axis="1 0 0" pos="0 0 0"/><joint type="hinge" axis="0 1 0" pos="0.1 0 0"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.02"/></body></worldbody></mujoco>"""
    with pytest.raises(ValueError, match="offset anchors"):
        torchsim.load_mjcf(xml, contact_model="articulated")
    with pytest.raises(ValueError, match="spring method only"):
        torchsim.load_mjcf(HOPPER, method="xpbd", contact_model="articulated")
    slide = """<mujoco><worldbody><body><joint type="slide" axis="1 0 0" frictionloss="1"/>
      <geom type="box" size="0.1 0.1 0.1"/></body></worldbody></mujoco>"""
    with pytest.raises(ValueError, match="frictionloss"):  # the tree's solve takes dry friction on hinges only
        torchsim.load_mjcf(slide, contact_model="articulated")
