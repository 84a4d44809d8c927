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
