"""Joint ``frictionloss``: dry friction on hinge and slide dofs, against MuJoCo and against exact Coulomb friction.

The pendulum is a 0.5 m capsule (1 kg) with a 1 kg ball at its tip on a hinge about y, starting horizontal: gravity
torque 7.36 N m, inertia about the hinge 0.344 kg m^2. MuJoCo's friction is a soft constraint (impedance 0.9, time
constant 0.02 s), so a held dof creeps and a sliding one lags ideal Coulomb friction a little; ours is a clamped
velocity-level impulse (``torchsim.joint_space``), so the exact Coulomb solution is the common reference.
"""

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from torchsim.io_mjcf import UnsupportedMJCFError

F64 = torch.float64
MJ_DT = 0.002


def pendulum(frictionloss, axis="0 1 0", armature=0.0, timestep=MJ_DT):
    return f"""<mujoco><option timestep="{timestep}"/><worldbody><body pos="0 0 1">
      <joint type="hinge" axis="{axis}" frictionloss="{frictionloss}" armature="{armature}"/>
      <geom type="capsule" fromto="0 0 0 0.5 0 0" size="0.05" mass="1" contype="0" conaffinity="0"/>
      <geom type="sphere" pos="0.5 0 0" size="0.1" mass="1" contype="0" conaffinity="0"/>
    </body></worldbody></mujoco>"""


def slider(frictionloss, timestep=MJ_DT):
    """A 2 kg box on a vertical slide: weight 19.6 N."""
    return f"""<mujoco><option timestep="{timestep}"/><worldbody><body pos="0 0 1">
      <joint type="slide" axis="0 0 1" frictionloss="{frictionloss}"/>
      <geom type="box" size="0.1 0.1 0.1" mass="2" contype="0" conaffinity="0"/>
    </body></worldbody></mujoco>"""


def mujoco_run(xml, qd0, duration, dt=MJ_DT, every=0.01):
    """MuJoCo's coordinate and rate ``(n,)`` every ``every`` seconds, from rest at 0 with rate ``qd0``."""
    m = mujoco.MjModel.from_xml_string(xml)
    m.opt.timestep = dt
    d = mujoco.MjData(m)
    d.qvel[0] = qd0
    q, qd = [], []
    per_sample = int(round(every / dt))
    for i in range(int(round(duration / dt))):
        mujoco.mj_step(m, d)
        if (i + 1) % per_sample == 0:
            q.append(d.qpos[0])
            qd.append(d.qvel[0])
    return np.array(q), np.array(qd)


def torchsim_run(xml, qd0, duration, method, substeps, every=0.01, contact_model="impulse"):
    """Ours, sampled every ``every`` seconds (the step length; ``substeps`` per step)."""
    sys = torchsim.load_mjcf(xml.replace(f'timestep="{MJ_DT}"', f'timestep="{every}"'), method=method, dtype=F64,
                             substeps=substeps, contact_model=contact_model)
    state = torchsim.init(sys, torch.zeros(1, 1, dtype=F64), torch.full((1, 1), float(qd0), dtype=F64))
    ctrl = torch.zeros(1, 0, dtype=F64)
    q, qd = [], []
    for _ in range(int(round(duration / every))):
        state = torchsim.step(sys, state, ctrl)
        q.append(state.q[0, 0].item())
        qd.append(state.qd[0, 0].item())
    assert not state.diverged.any()
    return np.array(q), np.array(qd)


def inertia_and_gravity_torque(xml):
    """The hinge's inertia [kg m^2] (armature included) and gravity torque [N m] at q = 0, from MuJoCo."""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    full = np.zeros((1, 1))
    mujoco.mj_fullM(m, d, full)
    return full[0, 0], -d.qfrc_bias[0]


def coulomb_pendulum(xml, frictionloss, duration, every=0.01, dt=1e-4):
    """Exact dry friction: ``I qdd = tau_g cos q - frictionloss sign(qd)``, sticking where ``|tau_g cos q| <=
    frictionloss`` at rest; semi-implicit steps of ``dt`` (10x below our substep), sampled every ``every``."""
    inertia, tau_g = inertia_and_gravity_torque(xml)
    q, qd, out = 0.0, 0.0, []
    per_sample = int(round(every / dt))
    for i in range(int(round(duration / dt))):
        tau = tau_g * np.cos(q)
        if qd != 0 or abs(tau) > frictionloss:
            direction = np.sign(qd) if qd != 0 else np.sign(tau)
            qd_new = qd + dt * (tau - frictionloss * direction) / inertia
            qd_new = 0.0 if qd != 0 and np.sign(qd_new) != np.sign(qd) else qd_new  # friction stops, never reverses
            q, qd = q + 0.5 * dt * (qd + qd_new), qd_new
        if (i + 1) % per_sample == 0:
            out.append(q)
    return np.array(out)


@pytest.mark.parametrize("method, substeps, duration", [("spring", 5, 1.0), ("xpbd", 20, 0.2)])
def test_held_pendulum_creeps_like_mujoco(method, substeps, duration):
    """frictionloss 8 N m > 7.36 N m gravity torque: the pendulum stays put, up to a creep.

    MuJoCo's soft friction creeps at a steady ~0.022 rad/s. Ours holds the hinge's relative rotation exactly each
    substep; the spring method's joint spring turns the link's fall into rotation within the substep, leaving
    ~0.006 rad over 1 s at h = 2 ms (0.0004 rad at the default 0.5 ms). XPBD's projection turns the link's linear
    momentum about the pivot into rotation after the friction impulse, which removes only the share
    ``I_com / I_pivot`` of it: the dof creeps at ``tau_g h / I_com`` (0.058 rad/s at h = 0.5 ms, 2.6x MuJoCo's;
    here 0.2 s at h = 0.5 ms to stay fast)."""
    xml = pendulum(8.0)
    mj_q, _ = mujoco_run(xml, 0.0, duration)
    ours, _ = torchsim_run(xml, 0.0, duration, method, substeps)
    print(f"{method}: creep over {duration} s: torchsim {ours[-1]:.5f} rad, MuJoCo {mj_q[-1]:.5f} rad")
    assert 0.0 < mj_q[-1] < 0.03 and abs(ours).max() <= abs(ours[-1]) + 1e-9  # a slow, steady creep downwards
    assert abs(ours[-1]) < {"spring": 0.5, "xpbd": 3.0}[method] * mj_q[-1]


@pytest.mark.parametrize("method, substeps, duration", [("spring", 10, 1.0), ("xpbd", 10, 0.5)])
def test_swinging_pendulum_follows_coulomb_friction_as_mujoco_does(method, substeps, duration):
    """frictionloss 3 N m < 7.36 N m: the pendulum swings down, turns at 2.11 rad (1 s covers the turn) and swings
    back. MuJoCo's soft friction (at 2 ms and at 0.5 ms) deviates from the exact Coulomb solution by up to 0.007 rad
    on this swing; ours (h = 1 ms) must stay within twice MuJoCo's deviation, and so within 3x of MuJoCo itself.
    A frictionloss 10% off moves the exact solution by 0.085 rad within 0.5 s (0.8 rad without friction)."""
    xml = pendulum(3.0)
    exact = coulomb_pendulum(xml, 3.0, duration)
    mj_q, _ = mujoco_run(xml, 0.0, duration)
    mj_fine, _ = mujoco_run(xml, 0.0, duration, dt=MJ_DT / 4)
    ours, _ = torchsim_run(xml, 0.0, duration, method, substeps)
    mj_error = max(abs(mj_q - exact).max(), abs(mj_fine - exact).max())
    print(f"{method}: max |q - exact| torchsim {abs(ours - exact).max():.4f}, MuJoCo dt {abs(mj_q - exact).max():.4f}, "
          f"dt/4 {abs(mj_fine - exact).max():.4f}; |torchsim - MuJoCo dt/4| {abs(ours - mj_fine).max():.4f} rad")
    assert abs(ours - exact).max() < 2 * mj_error
    assert abs(ours - mj_fine).max() < 3 * mj_error


def test_articulated_model_holds_and_swings_as_coulomb_friction():
    """The articulated model's tree solve (``torchsim.tree_solve``, its dry-friction sweep after the tree's rates):
    at frictionloss 8 N m the pendulum holds (it does not move; MuJoCo creeps 0.0224 rad in 1 s), at 3 N m
    it swings as the exact Coulomb solution within twice MuJoCo's deviation from it (the bars above; measured 0.0024
    rad, MuJoCo 0.0072)."""
    held, _ = torchsim_run(pendulum(8.0), 0.0, 1.0, "spring", 10, contact_model="articulated")
    assert abs(held).max() < 1e-9
    xml = pendulum(3.0)
    exact = coulomb_pendulum(xml, 3.0, 1.0)
    mj_error = max(abs(mujoco_run(xml, 0.0, 1.0, dt=dt)[0] - exact).max() for dt in (MJ_DT, MJ_DT / 4))
    swing, _ = torchsim_run(xml, 0.0, 1.0, "spring", 10, contact_model="articulated")
    print(f"max |q - exact| torchsim {abs(swing - exact).max():.4f}, MuJoCo {mj_error:.4f} rad")
    assert abs(swing - exact).max() < 2 * mj_error


@pytest.mark.parametrize("armature", [0.0, 0.3])
def test_spinning_hinge_decelerates_at_frictionloss_over_inertia(armature):
    """A vertical hinge (no gravity torque) spinning at 5 rad/s with frictionloss 0.5 N m decelerates at
    ``frictionloss / (I + armature)``, then stops and stays stopped. The armature checks that the impulse is sized by
    the inertia with the rotor."""
    xml = pendulum(0.5, axis="0 0 1", armature=armature)
    inertia, _ = inertia_and_gravity_torque(xml)
    alpha = 0.5 / inertia
    t = 0.01 * np.arange(1, 21)
    _, mj_qd = mujoco_run(xml, 5.0, 0.2)
    _, ours = torchsim_run(xml, 5.0, 0.2, "spring", 4)
    # from 0.05 s on: the joint spring first catches the link's centripetal pull (a 0.03 rad/s dip, friction or not)
    ours_alpha, mj_alpha = (-np.polyfit(t[4:], qd[4:], 1)[0] for qd in (ours, mj_qd))
    print(f"armature {armature}: deceleration torchsim {ours_alpha:.4f}, MuJoCo {mj_alpha:.4f}, "
          f"frictionloss / I {alpha:.4f} rad/s^2")
    assert abs(ours_alpha - alpha) < 0.01 * alpha and abs(ours_alpha - mj_alpha) < 0.01 * alpha
    _, stopping = torchsim_run(xml, 0.005, 0.05, "spring", 4)  # stops within a step: 0.005 rad/s < 0.01 s alpha
    assert abs(stopping).max() < 1e-9


@pytest.mark.parametrize("method", ["spring", "xpbd"])
def test_slide_holds_or_slips_at_frictionloss(method):
    """A 2 kg box on a vertical slide: frictionloss 25 N > 19.6 N holds it (MuJoCo creeps 0.3 mm in 0.1 s); with
    10 N it falls at ``g - 10 / 2 = 4.81 m/s^2`` (MuJoCo's fall after 0.1 s is matched to 0.5%)."""
    held, _ = torchsim_run(slider(25.0), 0.0, 0.1, method, 4)
    assert abs(held).max() < 1e-3
    mj_q, _ = mujoco_run(slider(10.0), 0.0, 0.1)
    ours, ours_qd = torchsim_run(slider(10.0), 0.0, 0.1, method, 4)
    print(f"{method}: slide after 0.1 s: torchsim {ours[-1]:.6f} m, MuJoCo {mj_q[-1]:.6f} m")
    np.testing.assert_allclose(ours_qd[-1], -(9.81 - 5.0) * 0.1, rtol=1e-3)
    np.testing.assert_allclose(ours[-1], mj_q[-1], rtol=5e-3)


def test_per_env_frictionloss():
    """``dof_frictionloss`` is batchable: each env of a batch with its own value matches a single-env run."""
    sys = torchsim.load_mjcf(pendulum(3.0), dtype=F64)
    values = torch.tensor([[1.0], [3.0], [8.0]], dtype=F64)
    batched = torchsim.init(sys.replace(dof_frictionloss=values), torch.zeros(3, 1, dtype=F64),
                            torch.zeros(3, 1, dtype=F64))
    singles = [torchsim.init(sys.replace(dof_frictionloss=v), torch.zeros(1, 1, dtype=F64),
                             torch.zeros(1, 1, dtype=F64)) for v in values]
    ctrl = torch.zeros(3, 0, dtype=F64)
    for _ in range(20):
        batched = torchsim.step(sys.replace(dof_frictionloss=values), batched, ctrl)
        singles = [torchsim.step(sys.replace(dof_frictionloss=v), s, ctrl[:1]) for v, s in zip(values, singles)]
    torch.testing.assert_close(batched.q, torch.cat([s.q for s in singles]))
    assert batched.q[0] > batched.q[1] > 10 * abs(batched.q[2])


def test_structure_decided_at_load():
    """Which dofs have friction is static: a model without it carries none (and its step does no friction work)."""
    sys = torchsim.load_mjcf(pendulum(0.0), dtype=F64)
    assert sys.dof_friction_hinges.numel() == 0 and not sys.dof_friction_slides
    sys = torchsim.load_mjcf(pendulum(1.0), dtype=F64)
    assert sys.dof_friction_hinges.tolist() == [0] and not sys.dof_friction_slides
    assert torchsim.load_mjcf(slider(1.0), dtype=F64).dof_friction_slides


@pytest.mark.parametrize("joint", ["free", "ball"])
def test_frictionloss_on_free_or_ball_joint_is_refused(joint):
    xml = f"""<mujoco><worldbody><body pos="0 0 1"><joint type="{joint}" frictionloss="0.1"/>
      <geom type="sphere" size="0.1"/></body></worldbody></mujoco>"""
    with pytest.raises(UnsupportedMJCFError, match="frictionloss on the free or ball joint"):
        torchsim.load_mjcf(xml)

