"""MuJoCo height fields (``<hfield>`` assets of ``type="hfield"`` geoms) -> the System's height-field tables
(``torchsim.collision_hfield`` collides them).

A height field must be static: its geom on the world body (or a body welded to it); one on a moving body is refused
by name. Its elevations are MuJoCo's compiled ``hfield_data`` (normalised to 0..1) times ``hfield_size[2]``: a
task that writes ``hfield_data`` at run time (dm_control's quadruped terrains) sets ``System.hfield_height``
(``sys.replace(hfield_height=...)``, one field for all envs); the XML's data (zeros where it has none) is what loads.
"""

import mujoco
import numpy as np
import torch

from torchsim.collision_hfield import window
from torchsim.io_mjcf.subset import UnsupportedMJCFError, name


def hfield_fields(m: mujoco.MjModel, groups: dict) -> dict:
    """``hfield_height (H,)`` [m] every field's vertex elevations (row-major, at MuJoCo's ``hfield_adr``),
    ``geom_hfield_adr (G,)`` (-1 for other geoms), ``geom_hfield_grid (G, 2)`` (nrow, ncol),
    ``geom_hfield_size (G, 4)`` (MuJoCo's ``hfield_size``) and ``hfield_windows``: for each kind ``*_hfield`` of
    ``groups`` (kind -> [(geom a, geom b, friction, margin, ...)]) its window ``(kind, Wy, Wx)`` in cells, the
    largest any pair of the kind needs (``collision_hfield.window`` of ``geom_rbound + margin``)."""
    height = np.zeros(m.nhfield and len(m.hfield_data))
    adr, grid, size = -np.ones(m.ngeom, int), np.zeros((m.ngeom, 2), int), np.zeros((m.ngeom, 4))
    for h in range(m.nhfield):
        a, n = m.hfield_adr[h], m.hfield_nrow[h] * m.hfield_ncol[h]
        height[a:a + n] = m.hfield_data[a:a + n] * m.hfield_size[h, 2]
    for g in range(m.ngeom):
        if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_HFIELD:
            h = m.geom_dataid[g]
            adr[g], grid[g], size[g] = m.hfield_adr[h], (m.hfield_nrow[h], m.hfield_ncol[h]), m.hfield_size[h]
    windows = []
    for kind, rows in sorted(groups.items()):
        if not kind.endswith("_hfield"):
            continue
        wy = wx = 1
        for ga, gb, _, margin, *_ in rows:
            if m.body_weldid[m.geom_bodyid[gb]] != 0:
                raise UnsupportedMJCFError(f"hfield geom {name(m, mujoco.mjtObj.mjOBJ_GEOM, gb)!r} is on a moving "
                                           "body; height fields must be static (on the world body)")
            (nrow, ncol), (sx, sy) = grid[gb], size[gb, :2]
            rb = m.geom_rbound[ga] + margin
            wx = max(wx, window(rb, 2 * sx / (ncol - 1), ncol - 1))
            wy = max(wy, window(rb, 2 * sy / (nrow - 1), nrow - 1))
        windows.append((kind, wy, wx))
    return dict(hfield_height=torch.as_tensor(height), geom_hfield_adr=torch.as_tensor(adr, dtype=torch.long),
                geom_hfield_grid=torch.as_tensor(grid, dtype=torch.long), geom_hfield_size=torch.as_tensor(size),
                hfield_windows=tuple(windows))
