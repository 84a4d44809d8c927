"""Rigid frames for the renderer: quaternions to rotation matrices, and every env's body frames read from a
``torchsim.State`` with the static world appended (ext index ``N``), then the mocap bodies' frames.

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


def body_frames(x_pos: torch.Tensor, x_quat: torch.Tensor, mocap_pos: torch.Tensor | None = None,
                mocap_quat: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Every body's frame with the world appended, then the mocap bodies' where given: positions
    ``(B, N + 1 + K, 3)`` (a body's centre of mass, as ``State.x_pos``) and rotations ``(B, N + 1 + K, 3, 3)`` from
    ``x_pos (B, N, 3)``, ``x_quat (B, N, 4)`` and ``mocap_pos (B, K, 3)``, ``mocap_quat (B, K, 4)`` (the frame
    indices of ``System.geom_frame``; ``-1`` selects the world only where there are no mocap frames)."""
    batch = x_pos.shape[0]
    eye = torch.eye(3, dtype=x_pos.dtype, device=x_pos.device).expand(batch, 1, 3, 3)
    pos = [x_pos, x_pos.new_zeros(batch, 1, 3)]
    rot = [quat_to_mat(x_quat), eye]
    if mocap_pos is not None:
        pos.append(mocap_pos)
        rot.append(quat_to_mat(mocap_quat))
    return torch.cat(pos, 1), torch.cat(rot, 1)


def place(pos: torch.Tensor, rot: torch.Tensor, body: torch.Tensor, local_pos: torch.Tensor,
          local_rot: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World frames ``(B, K, 3)``, ``(B, K, 3, 3)`` of ``K`` frames fixed on bodies ``body (K,)`` (ext indices into
    the frames of :func:`body_frames`) at ``local_pos (K, 3)``, ``local_rot (K, 3, 3)`` in the body's frame."""
    bpos, brot = pos[:, body], rot[:, body]
    return bpos + (brot @ local_pos.unsqueeze(-1)).squeeze(-1), brot @ local_rot
