"""Rigid frames for the renderer: quaternions to rotation matrices, and every env's body frames read from a
``torchsim.State`` with the static world appended (so that the world's ext index ``N`` and ``-1`` both select it).

Kept apart from the engine's lane-layout helpers: the renderer works batch-first, ``(B, ..., 3)`` / ``(B, ..., 3, 3)``.
"""

import numpy as np
import torch


def quat_to_mat(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``(..., 3, 3)`` of unit quaternions ``q (..., 4)`` (``wxyz``, MuJoCo's convention); the
    columns are the rotated frame's axes."""
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    rows = (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y))
    return torch.stack(rows, -1).reshape(*q.shape[:-1], 3, 3)


def quat_to_mat_np(q) -> np.ndarray:
    """:func:`quat_to_mat` for one float64 numpy quaternion (build time)."""
    return quat_to_mat(torch.as_tensor(np.asarray(q, dtype=np.float64))).numpy()


def body_frames(x_pos: torch.Tensor, x_quat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Every body's frame with the world appended: positions ``(B, N + 1, 3)`` (the body's centre of mass, as
    ``State.x_pos``) and rotations ``(B, N + 1, 3, 3)`` from ``x_pos (B, N, 3)``, ``x_quat (B, N, 4)``."""
    batch = x_pos.shape[0]
    pos = torch.cat((x_pos, x_pos.new_zeros(batch, 1, 3)), 1)
    rot = quat_to_mat(x_quat)
    eye = torch.eye(3, dtype=rot.dtype, device=rot.device).expand(batch, 1, 3, 3)
    return pos, torch.cat((rot, eye), 1)


def place(pos: torch.Tensor, rot: torch.Tensor, body: torch.Tensor, local_pos: torch.Tensor,
          local_rot: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World frames ``(B, K, 3)``, ``(B, K, 3, 3)`` of ``K`` frames fixed on bodies ``body (K,)`` (ext indices into
    the frames of :func:`body_frames`) at ``local_pos (K, 3)``, ``local_rot (K, 3, 3)`` in the body's frame."""
    bpos, brot = pos[:, body], rot[:, body]
    return bpos + (brot @ local_pos.unsqueeze(-1)).squeeze(-1), brot @ local_rot
