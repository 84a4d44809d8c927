"""Exact depth images of grid layouts with full-height walls (2.5D ray casting), batched in torch.

The camera sits at height ``height`` above the floor (z = 0), its axis horizontal along the agent's heading; walls
rise from the floor to the ceiling (``ceiling`` m; None: no ceiling). torchsim.render's pinhole convention
(docs/rendering.md): pixel ``(i, j)``, row 0 at the top, is sampled through its centre, the ray
``(X[j], Y[i], -1)`` in the camera frame with ``X[j] = (2 (j + 1/2) / W - 1) tan(hfov / 2)`` and
``Y[i] = (1 - 2 (i + 1/2) / H) tan(hfov / 2) H / W``. Depth is planar (along the camera axis).

Every image column is a vertical plane: one 2D ray per column, ``p + t (f + X[j] r)`` (``f`` the heading, ``r``
its right), is marched through the grid cell by cell (Amanatides-Woo DDA), so ``t`` at the first wall cell is the
planar depth of the wall in the whole column. A pixel of row ``i`` sees the wall if it is nearer than the floor
(``t = height / -Y[i]``, rows below the horizon) or the ceiling (``t = (ceiling - height) / Y[i]``, above). Depths
are clipped to ``max_depth``.
"""

import math

import torch


def column_rays(width: int, hfov_deg: float, device=None) -> torch.Tensor:
    """``X[j]``: the camera-frame x of column ``j``'s ray at unit forward distance."""
    t = math.tan(math.radians(hfov_deg) / 2)
    return (2 * (torch.arange(width, device=device) + 0.5) / width - 1) * t


def row_rays(height: int, width: int, hfov_deg: float, device=None) -> torch.Tensor:
    """``Y[i]``: the camera-frame y (up) of row ``i``'s ray at unit forward distance."""
    t = math.tan(math.radians(hfov_deg) / 2) * height / width
    return (1 - 2 * (torch.arange(height, device=device) + 0.5) / height) * t


def wall_distance(walls_flat: torch.Tensor, layout: torch.Tensor, pos: torch.Tensor, heading: torch.Tensor,
                  xs: torch.Tensor, size: int, cell: float, max_depth: float, check_every: int = 8) -> torch.Tensor:
    """Planar distance ``(B, W)`` to the first wall along each column's ray (``max_depth`` if none nearer).
    ``walls_flat (L, G * G)``, ``layout (B,)``, ``pos (B, 2)`` [m], ``heading (B,)`` [rad], ``xs (W,)``."""
    b, w = pos.shape[0], xs.shape[0]
    c, s = torch.cos(heading)[:, None], torch.sin(heading)[:, None]
    dx = c + xs * s           # f + X r, with f = (cos, sin), r = (sin, -cos)
    dy = s - xs * c
    px = pos[:, 0:1].expand(b, w)
    py = pos[:, 1:2].expand(b, w)
    cx = torch.floor(px / cell).long()
    cy = torch.floor(py / cell).long()
    step_x = torch.where(dx >= 0, 1, -1)
    step_y = torch.where(dy >= 0, 1, -1)
    inv_x = 1.0 / dx.abs().clamp_min(1e-12)
    inv_y = 1.0 / dy.abs().clamp_min(1e-12)
    t_x = torch.where(dx >= 0, (cx + 1) * cell - px, px - cx * cell) * inv_x   # t of the next x-line crossing
    t_y = torch.where(dy >= 0, (cy + 1) * cell - py, py - cy * cell) * inv_y
    dt_x, dt_y = cell * inv_x, cell * inv_y
    flat = walls_flat.reshape(-1)
    cur = layout[:, None] * (size * size) + cy.clamp(0, size - 1) * size + cx.clamp(0, size - 1)  # flat cell index
    inc_x, inc_y = step_x, step_y * size
    last = flat.numel() - 1
    hit = torch.full((b, w), max_depth, dtype=pos.dtype, device=pos.device)
    open_ = torch.ones((b, w), dtype=torch.bool, device=pos.device)
    # every step crosses one grid line; at most this many before t exceeds max_depth along the widest ray
    reach = max_depth * math.sqrt(1 + float(xs.abs().max()) ** 2) if w else 0.0
    n_steps = int(math.ceil(2 * reach / cell)) + 2
    t = torch.zeros_like(hit)
    for k in range(n_steps):
        go_x = t_x < t_y
        t = torch.minimum(t_x, t_y)
        cur = (cur + torch.where(go_x, inc_x, inc_y)).clamp_(0, last)   # a ray past its wall may leave the grid
        t_x = t_x + go_x * dt_x
        t_y = t_y + (~go_x) * dt_y
        wall = flat[cur] & open_
        hit = torch.where(wall, t, hit)
        open_ = open_ & ~wall
        if (k + 1) % check_every == 0:
            open_ &= t < max_depth
            if not bool(open_.any()):
                break
    return hit.clamp_max(max_depth)


def depth_image(wall_t: torch.Tensor, ys: torch.Tensor, height: float, ceiling: float | None,
                max_depth: float) -> torch.Tensor:
    """``(B, H, W)`` planar depth from the per-column wall distances ``wall_t (B, W)`` and row rays ``ys (H,)``."""
    floor_t = torch.where(ys < 0, height / (-ys).clamp_min(1e-12), torch.inf)
    if ceiling is not None:
        floor_t = torch.where(ys > 0, (ceiling - height) / ys.clamp_min(1e-12), floor_t)
    return torch.minimum(wall_t[:, None, :], floor_t[None, :, None]).clamp_max(max_depth)
