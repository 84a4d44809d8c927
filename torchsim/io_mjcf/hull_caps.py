"""Capping colliding meshes' convex hulls at load time (``load_mjcf(max_hull_vertices=N)``).

torchsim collides a mesh as the convex hull MuJoCo compiles for it, and refuses a hull of more than
``meshes.MAX_HULL_VERTICES`` vertices (its contacts test every hull vertex and face). MuJoCo's ``<mesh
maxhullvert="N">`` stops its hull computation at ``N`` vertices; this sets it, through ``mujoco.MjSpec``, on every
mesh of a colliding geom whose hull has more, and recompiles. The capped ``MjModel`` is the one the System is built
from, so MuJoCo (given that model) and torchsim collide the same hull.
"""

import numbers
import warnings
from collections.abc import Callable

import mujoco

from torchsim.io_mjcf.geoms import candidate_pairs
from torchsim.io_mjcf.meshes import MAX_HULL_VERTICES
from torchsim.io_mjcf.subset import name

#: MuJoCo's smallest ``maxhullvert`` (a hull needs 4 vertices).
MIN_HULL_VERTICES = 4


def check_max_hull_vertices(max_hull_vertices) -> None:
    """A cap must be an integer from ``MIN_HULL_VERTICES`` (MuJoCo's least) to ``MAX_HULL_VERTICES`` (torchsim's
    most)."""
    if (isinstance(max_hull_vertices, bool) or not isinstance(max_hull_vertices, numbers.Integral)
            or not MIN_HULL_VERTICES <= max_hull_vertices <= MAX_HULL_VERTICES):
        raise ValueError(f"max_hull_vertices must be an integer from {MIN_HULL_VERTICES} (MuJoCo's least "
                         f"maxhullvert) to {MAX_HULL_VERTICES} (the most hull vertices torchsim collides), got "
                         f"{max_hull_vertices!r}")


def hull_vertex_count(m: mujoco.MjModel, mesh: int) -> int:
    """Vertices of the convex hull MuJoCo compiled for ``mesh`` (0 where it compiled none)."""
    adr = m.mesh_graphadr[mesh]
    return int(m.mesh_graph[adr]) if adr >= 0 else 0


def colliding_meshes(m: mujoco.MjModel) -> list[int]:
    """The meshes of the mesh geoms that can collide (in a candidate contact pair), sorted."""
    if m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_CONTACT):
        return []
    with warnings.catch_warnings():  # what the pairs ignore (condim) is said once, by the loader's geom_fields
        warnings.simplefilter("ignore")
        geoms = {g for pair in candidate_pairs(m) for g in pair}
    return sorted({int(m.geom_dataid[g]) for g in geoms if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH})


def capped_model(m: mujoco.MjModel, parse: Callable[[], mujoco.MjSpec], max_hull_vertices: int) -> mujoco.MjModel:
    """Model ``m``, or where a colliding mesh's hull has more than ``max_hull_vertices`` vertices, its MJCF parsed
    afresh (``parse``: a compiled spec does not compile again) and compiled with MuJoCo's ``maxhullvert`` at
    ``max_hull_vertices`` on each such mesh; one warning names those meshes and their hulls' vertex counts before."""
    check_max_hull_vertices(max_hull_vertices)
    over = {mesh: n for mesh in colliding_meshes(m) if (n := hull_vertex_count(m, mesh)) > max_hull_vertices}
    if not over:
        return m
    spec = parse()
    for mesh in over:  # the spec's meshes are the model's, in order
        spec.meshes[mesh].maxhullvert = max_hull_vertices
    capped = spec.compile()
    listed = ", ".join(f"{name(m, mujoco.mjtObj.mjOBJ_MESH, mesh)!r} ({n})" for mesh, n in over.items())
    warnings.warn(f"max_hull_vertices={max_hull_vertices}: MuJoCo's maxhullvert caps the convex hulls of "
                  f"{len(over)} colliding meshes (their vertices before): {listed}; MuJoCo, given this model, "
                  "collides the same hulls", stacklevel=4)
    return capped
