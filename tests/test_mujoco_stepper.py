"""``MujocoStepper``: an env's task code on MuJoCo C's physics (policy transfer)."""

import mujoco
import numpy as np
import pytest
import torch

import torchsim.envs
from torchsim.execution.mujoco import MujocoStepper


def _stepper(name: str, dtype=torch.float64) -> MujocoStepper:
    probe = torchsim.envs.make(name, dtype=dtype)
    return MujocoStepper(probe.base_sys, probe.mj_model, threads=2)


def test_step_is_mujocos_step():
    """One call is one ``mj_step`` of the env's model: qpos and qvel equal MuJoCo's to rounding (float64; the
    State's q is re-read from the body poses, which moves it by ~1e-13)."""
    stepper = _stepper("ant")
    env = torchsim.envs.make("ant", num_envs=3, dtype=torch.float64, stepper=stepper)
    ctrl = torch.linspace(-1, 1, 3 * 8, dtype=torch.float64).reshape(3, 8)
    after = stepper(env.state, ctrl)
    m, d = env.mj_model, mujoco.MjData(env.mj_model)
    for b in range(3):
        d.qpos[:], d.qvel[:], d.ctrl[:] = env.state.q[b].numpy(), env.state.qd[b].numpy(), ctrl[b].numpy()
        mujoco.mj_step(m, d)
        np.testing.assert_allclose(after.q[b].numpy(), d.qpos, atol=1e-10)
        np.testing.assert_allclose(after.qd[b].numpy(), d.qvel, atol=1e-9)
    assert not after.diverged.any()


def test_substeps_split_mujocos_step():
    """With ``substeps=4`` one call is four ``mj_step`` s of a quarter of the model's timestep, the control held
    (the Ant starts standing on the floor: contacts act); the caller's model keeps its timestep; a substep count
    that is not a positive integer is refused."""
    probe = torchsim.envs.make("ant", dtype=torch.float64)
    dt = probe.mj_model.opt.timestep
    stepper = MujocoStepper(probe.base_sys, probe.mj_model, threads=2, substeps=4)
    assert probe.mj_model.opt.timestep == dt and stepper.model.opt.timestep == dt / 4
    # a reset's start (0.46-0.64 m up) may still be in the air: start from the Ant settled on its feet by MuJoCo
    rest = mujoco.MjData(probe.mj_model)
    while rest.time < 1.0:
        mujoco.mj_step(probe.mj_model, rest)
    start = torchsim.init(probe.base_sys, torch.from_numpy(rest.qpos).expand(2, -1).clone(),
                          torch.from_numpy(rest.qvel).expand(2, -1).clone())
    ctrl = torch.linspace(-1, 1, 2 * 8, dtype=torch.float64).reshape(2, 8)
    after = stepper(start, ctrl)
    m = probe.mj_model.__copy__()
    m.opt.timestep = dt / 4
    d = mujoco.MjData(m)
    for b in range(2):
        mujoco.mj_resetData(m, d)
        d.qpos[:], d.qvel[:], d.ctrl[:] = rest.qpos, rest.qvel, ctrl[b].numpy()
        for _ in range(4):
            mujoco.mj_step(m, d)
        assert d.ncon > 0
        np.testing.assert_allclose(after.q[b].numpy(), d.qpos, atol=1e-10)
        np.testing.assert_allclose(after.qd[b].numpy(), d.qvel, atol=1e-9)
    for bad in (0, 2.0, True):
        with pytest.raises(ValueError, match="substeps must be a positive integer"):
            MujocoStepper(probe.base_sys, probe.mj_model, substeps=bad)


def test_env_runs_on_mujoco_and_flags_a_reset():
    """An env on MuJoCo's physics steps like any other; an env MuJoCo resets (speeds past its 1e10 bound) keeps
    its last state and is flagged, the others run on."""
    stepper = _stepper("hopper", torch.float32)
    env = torchsim.envs.make("hopper", num_envs=4, stepper=stepper)
    td = env.rollout(5)
    assert torch.isfinite(td["next", "observation"]).all()
    state = env.state._replace(qd=env.state.qd.index_fill(0, torch.tensor([1]), 1e12))
    after = stepper(state, torch.zeros(4, env.sys.nu))
    assert after.diverged.tolist() == [False, True, False, False]
    torch.testing.assert_close(after.q[1], state.q[1], atol=1e-6, rtol=0)  # re-read from its body poses


def test_refuses_per_env_parameters():
    env = torchsim.envs.make("hopper", num_envs=2, stepper=_stepper("hopper", torch.float32))
    with pytest.raises(NotImplementedError, match="per-env physics parameters"):
        env.set_physics(mass_scale=1.1)
