"""Cart-pole balancing tasks (Brax's definitions): keep one pole, or two stacked poles, upright."""

import torch

from torchsim import spatial
from torchsim.envs.base import TorchsimEnv


class InvertedPendulum(TorchsimEnv):
    """Cart on a rail with one hinged pole (``inverted_pendulum.xml``), ``dt = 2 x 20 ms``.

    Observation (4): cart position, pole angle, their rates. Action (1) in [-1, 1] mapped to ctrlrange [-3, 3].
    Reward: 1 per step. Terminates when |pole angle| > 0.2 rad. Reset: U(-0.01, 0.01) on q and qd.
    Versus MuJoCo (1 s, actions at 0.1x range): within 0.005 (MuJoCo's own 20 ms vs 5 ms: 0.005).
    """

    model_file = "inverted_pendulum.xml"
    frame_skip = 2
    substeps = 10  # 2 ms: contact-free, within MuJoCo's own timestep sensitivity (model header)
    observation_size = 4
    noise_q = ("uniform", 0.01)
    noise_qd = ("uniform", 0.01)

    def _observation(self, state, ctrl):
        return torch.cat((state.q, state.qd), -1)

    def _reward(self, before, after, ctrl):
        return torch.ones_like(after.q[:, 0])

    def _terminated(self, state):
        return state.q[:, 1].abs() > 0.2


class InvertedDoublePendulum(TorchsimEnv):
    """Cart with two stacked hinged poles (``inverted_double_pendulum.xml``), ``dt = 2 x 10 ms``.

    Observation (8): cart position, sin and cos of the 2 hinge angles, ``clip(qd, -10, 10)`` (3). Action (1).
    Reward: ``10 (1 - terminated) - 0.01 x_tip^2 - (z_tip - 2)^2 - 1e-3 w1^2 - 5e-3 w2^2`` (tip: 0.6 m along the upper pole from
    its hinge; w: hinge rates). Terminates when the tip is at or below z = 1 m. Reset: U(-0.1, 0.1) on q,
    0.1 N(0, 1) on qd. Versus MuJoCo (1 s, actions at 0.02x range): within 0.045 rad (MuJoCo's own 10 ms vs
    2.5 ms: 0.032 rad).
    """

    model_file = "inverted_double_pendulum.xml"
    frame_skip = 2
    substeps = 5  # 2 ms: contact-free, within MuJoCo's own timestep sensitivity (model header)
    observation_size = 8
    named_bodies = ("pole2",)
    pole_length = 0.6

    def _tip(self, state):
        pos, quat = self.mj_body_poses(state)
        axis = torch.tensor([0.0, 0.0, self.pole_length], dtype=pos.dtype, device=pos.device)
        return pos[:, 0] + spatial.batch_first.quat_rotate(quat[:, 0], axis)

    def _observation(self, state, ctrl):
        angles = state.q[:, 1:]
        return torch.cat((state.q[:, :1], torch.sin(angles), torch.cos(angles), state.qd.clamp(-10.0, 10.0)), -1)

    def _reward(self, before, after, ctrl):
        tip = self._tip(after)
        w1, w2 = after.qd[:, 1], after.qd[:, 2]
        alive = (tip[:, 2] > 1.0).to(tip.dtype)
        return 10.0 * alive - 0.01 * tip[:, 0] ** 2 - (tip[:, 2] - 2.0) ** 2 - 1e-3 * w1 ** 2 - 5e-3 * w2 ** 2

    def _terminated(self, state):
        return self._tip(state)[:, 2] <= 1.0
