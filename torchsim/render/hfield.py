"""Height fields for the renderer: each ``<hfield>`` is triangulated once, at scene build, into the closed solid
MuJoCo's renderer draws, and then drawn through the mesh path (:mod:`torchsim.render.mesh`: a BVH, in the geom's
frame).

MuJoCo's renderer (``mjr_uploadHField``) draws, in the hfield geom's frame:

- the top surface: grid vertex ``(row, col)`` at ``x = (2 col / (ncol - 1) - 1) size_x``,
  ``y = (2 row / (nrow - 1) - 1) size_y``, ``z = data[row, col] size_z`` (``hfield_data``, normalised to 0..1),
  each cell split along its diagonal from ``(row, col)`` to ``(row + 1, col + 1)`` (the triangles MuJoCo also
  collides, :mod:`torchsim.collision_hfield`);
- four side walls, from the base elevation ``z = -size[3]`` up to the surface's edge (one quad per edge cell);
- the bottom, at ``z = -size[3]``.

The same triangles here, wound outward (the mesh path tests both faces; the winding only orients the shading
normal, whose sign lambert shading ignores).
"""

import numpy as np


def triangulate(elevation: np.ndarray, size) -> tuple[np.ndarray, np.ndarray]:
    """Vertices ``(V, 3)`` and triangles ``(F, 3)`` of a height field with vertex elevations ``elevation
    (nrow, ncol)`` [m] (``hfield_data`` times ``size[2]``) and MuJoCo ``hfield_size`` ``size`` (x, y half sizes,
    elevation scale, base depth): ``2 (nrow-1)(ncol-1)`` surface triangles, ``4 (nrow + ncol - 2)`` wall triangles
    and 2 bottom triangles."""
    z = np.asarray(elevation, dtype=np.float64)
    nrow, ncol = z.shape
    if nrow < 2 or ncol < 2:
        raise ValueError(f"a height field needs at least 2 x 2 vertices, got {nrow} x {ncol}")
    sx, sy, _, base = (float(s) for s in size)
    x = (2.0 * np.arange(ncol) / (ncol - 1) - 1.0) * sx
    y = (2.0 * np.arange(nrow) / (nrow - 1) - 1.0) * sy
    top = np.stack(np.broadcast_arrays(x[None, :], y[:, None], z), -1).reshape(-1, 3)
    index = np.arange(nrow * ncol).reshape(nrow, ncol)
    a, b = index[:-1, :-1].ravel(), index[:-1, 1:].ravel()  # (row, col), (row, col + 1)
    c, d = index[1:, :-1].ravel(), index[1:, 1:].ravel()  # (row + 1, col), (row + 1, col + 1)
    surface = np.concatenate((np.stack((c, a, d), 1), np.stack((a, b, d), 1)))  # both up: +z normals
    # the rim, counter-clockwise seen from above (rows run along +y): each grid vertex once
    rim = np.concatenate((index[0, :-1], index[:-1, -1], index[-1, :0:-1], index[:0:-1, 0]))
    n = len(rim)
    low = top[rim] * np.array([1.0, 1.0, 0.0]) + np.array([0.0, 0.0, -base])
    lo = nrow * ncol + np.arange(n)  # the base vertex under each rim vertex
    hi, hi_next, lo_next = rim, np.roll(rim, -1), np.roll(lo, -1)
    walls = np.concatenate((np.stack((hi, lo, lo_next), 1), np.stack((hi, lo_next, hi_next), 1)))  # outward
    corner = lo[[0, ncol - 1, ncol + nrow - 2, 2 * ncol + nrow - 3]]  # (-x,-y), (+x,-y), (+x,+y), (-x,+y)
    bottom = np.array([[corner[0], corner[2], corner[1]], [corner[0], corner[3], corner[2]]])  # -z
    return np.concatenate((top, low)), np.concatenate((surface, walls, bottom)).astype(np.int64)


def elevation(model, hfield: int, system=None) -> np.ndarray:
    """Vertex elevations ``(nrow, ncol)`` [m] of height field ``hfield`` of a ``mujoco.MjModel``: the System's
    ``hfield_height`` where given (what it collides: a task may have replaced it), else MuJoCo's ``hfield_data``
    times ``hfield_size[2]``."""
    nrow, ncol = int(model.hfield_nrow[hfield]), int(model.hfield_ncol[hfield])
    adr = int(model.hfield_adr[hfield])
    height = getattr(system, "hfield_height", None) if system is not None else None
    if height is not None and int(height.shape[0]) == len(model.hfield_data):
        values = height[adr:adr + nrow * ncol].detach().cpu().double().numpy()
    else:
        values = np.asarray(model.hfield_data[adr:adr + nrow * ncol], np.float64) * model.hfield_size[hfield, 2]
    return values.reshape(nrow, ncol)


__all__ = ["elevation", "triangulate"]
