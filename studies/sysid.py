"""System identification through torchsim's gradients: recover masses and a friction
coefficient from a MuJoCo trajectory of a model whose masses and friction were perturbed.

    OMP_NUM_THREADS=1 python studies/sysid.py            # prints the fit and the recovered values

The scene (``SCENE``): a two-link arm on hinges about y (no contacts), driven by two motors, and a box on slides
along x and z resting on a plane, pushed along x by a third motor. The nominal model has link masses 1.0 and 0.6
kg, a 1.0 kg box and box-floor friction 0.8. MuJoCo (4.0, its default Euler integrator and soft contacts, 1 ms
steps) rolls out the *true* model, every body's mass and inertia scaled by ``TRUE_SCALES`` and the friction set to
``TRUE_FRICTION``, for ``SECONDS`` s under smooth random controls (sums of sines; the push sometimes beats the
friction, sometimes not), recorded every 10 ms.

The fit (torchsim, float64, eager, the spring method with ``contact_model="soft"``, 10 ms steps of 5 substeps)
starts from the nominal model and adjusts four log-scales: the three masses (each body's inertia scaled with its
mass) and the friction. The data are cut into windows of ``WINDOW`` steps (multiple shooting): every window
starts from MuJoCo's recorded state, all windows run as one batch, and the loss is the mean squared difference of
the predicted and recorded ``qpos`` and ``qvel`` over each window, every coordinate divided by its spread over
the trajectory. Short windows keep the gradient well conditioned (no long chaotic horizon) and the batch does
every window at once. The parameters take Adam steps on that loss (the rate decaying to 1% over the run), then the
result is reported against the truth.

What limits the recovery is the model gap, not the optimiser: torchsim's friction is a Coulomb-capped impulse
where MuJoCo's is a soft constraint (it creeps), and its joints are stiff springs where MuJoCo's are exact, so the
loss at the true parameters is not zero. The same fit on a trajectory that torchsim itself generated
(``--self``) recovers the parameters to the optimiser's tolerance, which separates the two.
"""

import argparse
import math
import time

import mujoco
import numpy as np
import torch

import torchsim

SCENE = """
<mujoco model="sysid">
  <option timestep="{timestep}"/>
  <default><joint damping="0.05" armature="0.01"/></default>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.1" friction="{friction} 0.005 0.0001"/>
    <body name="link1" pos="0 -1 1">
      <joint name="shoulder" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.04" mass="{m1}" contype="0" conaffinity="0"/>
      <body name="link2" pos="0.3 0 0">
        <joint name="elbow" type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0.25 0 0" size="0.03" mass="{m2}" contype="0" conaffinity="0"/>
      </body>
    </body>
    <body name="box" pos="0 0.5 0.05">
      <joint name="box_x" type="slide" axis="1 0 0" damping="0" armature="0"/>
      <joint name="box_z" type="slide" axis="0 0 1" damping="0" armature="0"/>
      <geom name="box" type="box" size="0.1 0.07 0.05" mass="{m3}" friction="{friction} 0.005 0.0001"/>
    </body>
  </worldbody>
  <actuator>
    <motor joint="shoulder" gear="1" ctrlrange="-6 6" ctrllimited="true"/>
    <motor joint="elbow" gear="1" ctrlrange="-3 3" ctrllimited="true"/>
    <motor joint="box_x" gear="1" ctrlrange="-20 20" ctrllimited="true"/>
  </actuator>
</mujoco>
"""
BODIES = ("link1", "link2", "box")
NOMINAL_MASSES = (1.0, 0.6, 1.0)
NOMINAL_FRICTION = 0.8
TRUE_SCALES = (1.3, 0.75, 1.5)
TRUE_FRICTION = 0.5
STEP = 0.01
SECONDS = 3.0
WINDOW = 5
CONTACT_MODEL = "soft"  # MuJoCo's soft normal (torchsim.soft_contacts): the box rests as deep as in MuJoCo
FITTED = [0, 1, 2, 4, 5, 6]  # qpos shoulder, elbow, box x; qvel the same


def controls(steps, seed=0):
    """Smooth random controls ``(steps, 3)``: per motor a sum of four sines of random frequency and phase."""
    rng = np.random.default_rng(seed)
    t = np.arange(steps) * STEP
    amp = np.array([3.0, 1.5, 16.0])
    u = np.zeros((steps, 3))
    for k in range(3):
        for _ in range(4):
            f, phase = rng.uniform(0.3, 2.0), rng.uniform(0, 2 * np.pi)
            u[:, k] += amp[k] / 2 * np.sin(2 * np.pi * f * t + phase)
    return u


def mujoco_trajectory(steps, ctrl, noslip=0):
    """The true model's ``qpos, qvel`` ``(steps + 1, n)`` under ``ctrl``, MuJoCo at 1 ms, recorded every step;
    ``noslip``: MuJoCo's ``noslip_iterations`` (0, its default: soft friction, which creeps)."""
    masses = {f"m{i + 1}": m * s for i, (m, s) in enumerate(zip(NOMINAL_MASSES, TRUE_SCALES))}
    # the true masses written into the MJCF (each geom's inertia follows its mass): scaling model.body_mass after
    # compiling leaves MuJoCo's mass matrix at the old masses until mj_setConst (MuJoCo 4.0: a 1.5x box then
    # accelerated at F / 1 kg under 1.5x gravity)
    model = mujoco.MjModel.from_xml_string(SCENE.format(timestep=0.001, friction=TRUE_FRICTION, **masses))
    model.opt.noslip_iterations = noslip
    data = mujoco.MjData(model)
    data.qpos[:] = [0.4, -0.6, 0.0, -0.0005]
    mujoco.mj_forward(model, data)
    qpos, qvel = [data.qpos.copy()], [data.qvel.copy()]
    sub = round(STEP / model.opt.timestep)
    for k in range(steps):
        data.ctrl[:] = ctrl[k]
        mujoco.mj_step(model, data, nstep=sub)
        qpos.append(data.qpos.copy())
        qvel.append(data.qvel.copy())
    return np.array(qpos), np.array(qvel)


def load(friction=NOMINAL_FRICTION):
    masses = {f"m{i + 1}": m for i, m in enumerate(NOMINAL_MASSES)}
    return torchsim.load_mjcf(SCENE.format(timestep=STEP, friction=friction, **masses), dtype=torch.float64, substeps=5,
                              contact_model=CONTACT_MODEL)


def with_parameters(sys, log_scales, mass_rows):
    """``sys`` with body ``mass_rows``' masses and inertias scaled by ``exp(log_scales[:3])`` and every contact
    pair's friction by ``exp(log_scales[3])``."""
    scale = torch.ones_like(sys.body_mass).index_put((mass_rows,), torch.exp(log_scales[:3]))
    return sys.replace(body_mass=sys.body_mass * scale, body_inertia=sys.body_inertia * scale[:, None, None],
                       contact_groups=tuple(g._replace(friction=g.friction * torch.exp(log_scales[3]))
                                            for g in sys.contact_groups))


def window_loss(sys, q, qd, ctrl, starts, spread):
    """Mean squared, spread-normalised error of windows of ``WINDOW`` steps from the recorded states at
    ``starts`` (one env each), against the recording. The box's height and vertical speed are left out: they
    follow the two contact models' different rest dynamics (mm and cm/s), not the parameters."""
    state = torchsim.init(sys, q[starts], qd[starts])
    err = 0.0
    for k in range(WINDOW):
        state = torchsim.step(sys, state, ctrl[starts + k])
        pred = torch.cat((state.q, state.qd), -1)
        true = torch.cat((q[starts + k + 1], qd[starts + k + 1]), -1)
        err = err + (((pred - true) / spread)[:, FITTED] ** 2).mean()
    return err / WINDOW


def fit(sys, q, qd, ctrl, iterations, lr):
    mass_rows = torch.tensor([sys.body_names.index(n) for n in BODIES])
    spread = torch.cat((q, qd), -1).std(0).clamp_min(0.01)  # the box rests on z: no spread there
    starts = torch.arange(0, q.shape[0] - WINDOW - 1, 3)
    theta = torch.zeros(4, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.Adam([theta], lr=lr)
    decay = torch.optim.lr_scheduler.ExponentialLR(opt, 0.01 ** (1 / iterations))  # to 1% of lr at the end
    t0 = time.perf_counter()
    for it in range(iterations + 1):
        opt.zero_grad()
        loss = window_loss(with_parameters(sys, theta, mass_rows), q, qd, ctrl, starts, spread)
        if it == iterations:
            break
        loss.backward()
        opt.step()
        decay.step()
        if it % 10 == 0:
            print(f"iter {it:3d}  loss {loss.item():.3e}  masses x {np.exp(theta[:3].tolist()).round(4)}  "
                  f"friction x {math.exp(theta[3].item()):.4f}  ({time.perf_counter() - t0:.0f} s)", flush=True)
    return theta.detach(), loss.item(), len(starts)


def report(sys, theta, loss, windows):
    rows = [sys.body_names.index(n) for n in BODIES]
    print(f"\nfinal loss {loss:.3e} over {windows} windows of {WINDOW} steps")
    print(f"{'parameter':12s} {'nominal':>9s} {'true':>9s} {'recovered':>10s} {'error':>8s}")
    scales = np.exp(theta.numpy())
    for i, name in enumerate(BODIES):
        m0 = sys.body_mass[rows[i]].item()
        true, got = m0 * TRUE_SCALES[i], m0 * scales[i]
        print(f"{name + ' mass':12s} {m0:9.4f} {true:9.4f} {got:10.4f} {100 * (got / true - 1):+7.2f}%")
    got = NOMINAL_FRICTION * scales[3]
    print(f"{'friction':12s} {NOMINAL_FRICTION:9.4f} {TRUE_FRICTION:9.4f} {got:10.4f} "
          f"{100 * (got / TRUE_FRICTION - 1):+7.2f}%")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--iterations", type=int, default=120)
    parser.add_argument("--lr", type=float, default=0.05)
    parser.add_argument("--noslip", type=int, default=0, help="MuJoCo's noslip_iterations for the data")
    parser.add_argument("--self", dest="self_data", action="store_true",
                        help="fit a trajectory torchsim generated from the true parameters instead of MuJoCo's")
    args = parser.parse_args()
    torch.set_num_threads(1)
    steps = round(SECONDS / STEP)
    u = controls(steps)
    sys = load()
    ctrl = torch.tensor(u)
    if args.self_data:
        truth = with_parameters(sys, torch.log(torch.tensor(TRUE_SCALES + (TRUE_FRICTION / NOMINAL_FRICTION,),
                                                            dtype=torch.float64)),
                                torch.tensor([sys.body_names.index(n) for n in BODIES]))
        state = torchsim.init(truth, torch.tensor([[0.4, -0.6, 0.0, -0.0005]], dtype=torch.float64),
                              torch.zeros(1, 4, dtype=torch.float64))
        q, qd = [state.q[0]], [state.qd[0]]
        with torch.no_grad():
            for k in range(steps):
                state = torchsim.step(truth, state, ctrl[k:k + 1])
                q.append(state.q[0])
                qd.append(state.qd[0])
        q, qd = torch.stack(q), torch.stack(qd)
        print("data: torchsim's own rollout of the true parameters")
    else:
        qpos, qvel = mujoco_trajectory(steps, u, args.noslip)
        q, qd = torch.tensor(qpos), torch.tensor(qvel)
        print(f"data: MuJoCo {mujoco.__version__} (noslip_iterations {args.noslip}), {steps} steps of {STEP} s; box x "
              f"travels {qpos[:, 2].min():.3f} .. {qpos[:, 2].max():.3f} m, moving (|v| > 1 cm/s) "
              f"{100 * np.mean(np.abs(qvel[:, 2]) > 0.01):.0f}% of the time")
    theta, loss, windows = fit(sys, q, qd, ctrl, args.iterations, args.lr)
    report(sys, theta, loss, windows)


if __name__ == "__main__":
    main()
