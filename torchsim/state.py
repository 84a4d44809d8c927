"""The dynamic state that flows through :func:`torchsim.step`."""

from typing import NamedTuple

import torch


class State(NamedTuple):
    """Batched simulator state; ``B`` envs, ``N`` moving bodies (jointless bodies fused into their parent).

    Maximal coordinates are the source of truth; ``q``/``qd`` are read back from them after every step.

    Attributes:
        x_pos: (B, N, 3) centre-of-mass position in the world frame [m].
        x_quat: (B, N, 4) orientation of the body frame (MuJoCo's ``xquat``), unit quaternion ``wxyz``.
        xd_vel: (B, N, 3) linear velocity of the centre of mass, world frame [m/s].
        xd_ang: (B, N, 3) angular velocity, world frame [rad/s].
        q: (B, nq) generalized coordinates in MuJoCo's ``qpos`` layout; hinge angles continuous through full
            turns, as MuJoCo's.
        qd: (B, nv) generalized velocities in MuJoCo's ``qvel`` layout.
        diverged: (B,) bool; set (and kept) once an env's state went non-finite or out of bounds. A diverged
            env is frozen at its last good state until it is re-initialised.
        act: (B, na) the actuators' activations (MuJoCo's ``act``, ``torchsim.activation``); ``(B, 0)`` for a model
            without activation dynamics.
    """

    x_pos: torch.Tensor
    x_quat: torch.Tensor
    xd_vel: torch.Tensor
    xd_ang: torch.Tensor
    q: torch.Tensor
    qd: torch.Tensor
    diverged: torch.Tensor
    act: torch.Tensor
