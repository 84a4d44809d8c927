"""Procedural indoor layouts on an occupancy grid, and kinematic agent motion with wall sliding.

A layout is a ``(G, G)`` bool grid (True = wall, full height) of square cells ``cell`` metres wide: cell ``(i, j)``
covers ``x in [j c, (j+1) c]``, ``y in [i c, (i+1) c]``. :func:`generate_layout` splits the floor recursively into
rooms (binary space partition): each split is a one-cell wall crossing its rectangle, with one door (or, now and
then, a wide opening) in it; the outer border is wall. Every room is therefore reachable. The same seed gives the
same layout (NumPy's PCG64 generator).
"""

import numpy as np
import torch
import torch.nn.functional as F


def generate_layout(seed: int, size: int = 64, min_room: int = 10, max_room: int = 22, door: tuple = (4, 6),
                    open_prob: float = 0.15) -> torch.Tensor:
    """A ``(size, size)`` bool wall grid from ``seed``. Rooms are at least ``min_room`` cells wide inside; a
    rectangle is split while a side exceeds ``max_room`` (or, at random, while it can still hold two rooms); doors
    are ``door[0]..door[1]`` cells wide; with probability ``open_prob`` a split wall is mostly open instead."""
    rng = np.random.default_rng(int(seed))
    wall = np.zeros((size, size), dtype=bool)
    wall[0, :] = wall[-1, :] = wall[:, 0] = wall[:, -1] = True
    doors = []  # (axis of the wall line, line index, first cell, end cell): no later wall may cut a door

    def blocked(axis, k, lo, hi):
        # a wall along `axis` at index k spanning [lo, hi) would end on a door of the perpendicular walls
        return any(a != axis and s - 1 <= k <= e and (line == lo - 1 or line == hi) for a, line, s, e in doors)

    def split(r0, r1, c0, c1):  # interior rectangle rows [r0, r1), cols [c0, c1)
        h, w = r1 - r0, c1 - c0
        can_h, can_w = h >= 2 * min_room + 1, w >= 2 * min_room + 1
        if not (can_h or can_w):
            return
        if max(h, w) <= max_room and rng.random() < 0.35:
            return
        axis = 0 if (can_h and (h > w or not can_w or (h == w and rng.random() < 0.5))) else 1
        n = h if axis == 0 else w
        start = r0 if axis == 0 else c0
        lo, hi = (c0, c1) if axis == 0 else (r0, r1)
        options = [k for k in range(start + min_room, start + n - min_room) if not blocked(axis, k, lo, hi)]
        if not options:
            return
        k = int(rng.choice(options))
        span = hi - lo
        if rng.random() < open_prob:   # an open-plan partition: a wall stub at each end
            stub = int(rng.integers(1, max(2, span // 4)))
            opening = (lo + stub, hi - stub)
        else:
            width = int(rng.integers(door[0], door[1] + 1))
            s = int(rng.integers(lo + 1, hi - width))
            opening = (s, s + width)
        line = wall[k] if axis == 0 else wall[:, k]        # a view: writes go into `wall`
        line[lo:hi] = True
        line[opening[0]:opening[1]] = False
        # an end meeting a wide opening of the perpendicular wall stays free: no zigzag gaps with the wall of the
        # rectangle on the other side of that opening
        if not line[lo - 1]:
            line[lo:lo + door[0] + 1] = False
        if not line[hi]:
            line[hi - door[0] - 1:hi] = False
        run = 0
        for x in range(lo, hi + 1):       # no wall fragment shorter than 3 cells (0.6 m) on the new line
            if x < hi and line[x]:
                run += 1
                continue
            if 0 < run < 3:
                line[x - run:x] = False
            run = 0
        if opening[1] - opening[0] > 2 * door[0] + 2:   # a wide opening: later walls may meet it, not near its ends
            doors.append((axis, k, opening[0], opening[0] + door[0] + 1))
            doors.append((axis, k, opening[1] - door[0] - 1, opening[1]))
        else:
            doors.append((axis, k, *opening))
        if axis == 0:
            split(r0, k, c0, c1)
            split(k + 1, r1, c0, c1)
        else:
            split(r0, r1, c0, k)
            split(r0, r1, k + 1, c1)

    split(1, size - 1, 1, size - 1)
    return torch.from_numpy(wall)


def navigable(walls: torch.Tensor) -> torch.Tensor:
    """Cells whose 3x3 neighbourhood is wall-free ``(..., G, G)``: where an agent of half-width < 1.5 cells (but
    above half a cell) may stand at the cell's centre with clearance."""
    w = walls.reshape(-1, 1, *walls.shape[-2:]).float()
    near = F.max_pool2d(w, 3, stride=1, padding=1) > 0
    return (~near).reshape(walls.shape)


def slide_move(walls_flat: torch.Tensor, layout: torch.Tensor, pos: torch.Tensor, delta: torch.Tensor,
               size: int, cell: float, radius: float, max_step: float = 0.25) -> torch.Tensor:
    """Move agents (axis-aligned square footprint of half-width ``radius``) from ``pos (B, 2)`` by ``delta (B, 2)``
    [m], first along x, then along y; a move blocked by a wall stops ``1e-4`` m short of it, so the agent slides
    along walls. ``walls_flat (L, G * G)`` bool, ``layout (B,)`` each agent's layout; ``|delta| <= max_step``."""
    steps = int(np.ceil(max_step / cell)) + 2
    out = pos.clone()
    for axis in (0, 1):
        other = 1 - axis
        lo_o = torch.floor((out[:, other] - radius) / cell).long()
        n_o = int(np.ceil(2 * radius / cell)) + 1
        across = lo_o[:, None] + torch.arange(n_o, device=pos.device)  # (B, n_o) rows (x moves) the footprint spans
        inside = across <= torch.floor((out[:, other] + radius) / cell).long()[:, None]
        across = across.clamp(0, size - 1)
        d = delta[:, axis]
        sgn = torch.where(d >= 0, 1, -1)
        edge = out[:, axis] + sgn * radius                         # leading edge
        base = torch.floor(edge / cell).long()
        along = base[:, None] + sgn[:, None] * torch.arange(steps, device=pos.device)  # (B, steps)
        along_c = along.clamp(0, size - 1)
        if axis == 0:   # x moves: columns `along`, rows `across`
            idx = across[:, :, None] * size + along_c[:, None, :]
        else:
            idx = along_c[:, None, :] * size + across[:, :, None]
        hit = (walls_flat[layout[:, None, None].expand_as(idx), idx] & inside[:, :, None]).any(1)  # (B, steps)
        face = torch.where(sgn[:, None] > 0, along * cell, (along + 1) * cell)   # the wall face met first
        ahead = torch.where(sgn[:, None] > 0, face >= edge[:, None] - 1e-6, face <= edge[:, None] + 1e-6)
        limit_fwd = torch.where(hit & ahead, face - radius - 1e-4, torch.inf).amin(1)
        limit_bwd = torch.where(hit & ahead, face + radius + 1e-4, -torch.inf).amax(1)
        target = out[:, axis] + d
        moved = torch.where(sgn > 0, torch.minimum(target, limit_fwd), torch.maximum(target, limit_bwd))
        # never move backwards because of a wall (a position already touching stays put)
        moved = torch.where(sgn > 0, torch.maximum(moved, out[:, axis]), torch.minimum(moved, out[:, axis]))
        out[:, axis] = moved
    return out


def collides(walls: torch.Tensor, pos: torch.Tensor, cell: float, radius: float) -> torch.Tensor:
    """Whether the square footprints at ``pos (B, 2)`` overlap a wall of ``walls (B, G, G)`` (for tests)."""
    g = walls.shape[-1]
    lo = torch.floor((pos - radius) / cell).long().clamp(0, g - 1)
    hi = torch.floor((pos + radius) / cell).long().clamp(0, g - 1)
    out = []
    for b in range(pos.shape[0]):
        out.append(bool(walls[b, lo[b, 1]:hi[b, 1] + 1, lo[b, 0]:hi[b, 0] + 1].any()))
    return torch.tensor(out)
