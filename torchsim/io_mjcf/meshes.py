"""Mesh geoms -> their convex hulls, as MuJoCo collides them (``torchsim.collision_mesh`` reads them).

MuJoCo collides a mesh as the convex hull it computes at compile time (``MjModel.mesh_graph``: per mesh
``numvert, numface, vert_edgeadr[numvert], vert_globalid[numvert], edge_localid[numvert + 3 numface],
face_globalid[3 numface]``, the hull's vertices and triangles as indices into the mesh's ``mesh_vert``). Mesh
vertices are in the mesh frame, which MuJoCo's compiler aligns with the geom frame (it moves the mesh to its
centroid and principal axes and folds that pose into ``geom_pos``/``geom_quat``), so the hull is in the geom
frame as it is.

Every colliding mesh's hull is padded to the model's largest, so that a contact group's shapes are static: its
vertices repeat the first (masked off: ``geom_hull_real``) and its face planes repeat the first (a maximum over
planes is unchanged by a repeat). Coplanar hull triangles are merged into one plane. Each vertex keeps its edges to
its neighbours on the hull (the separating-axis contact's edge pairs).
"""

import mujoco
import numpy as np
import torch

from torchsim.io_mjcf.subset import UnsupportedMJCFError, name

#: The most hull vertices a colliding mesh may have. Contacts test every hull vertex against the other geom's face
#: planes and both hulls' vertices along every face normal and edge-pair axis (``torchsim.collision_mesh``): a
#: mesh-mesh pair of 64-vertex hulls (up to 124 faces each) costs 16k plane tests, 32k projections on the face
#: normals and 2 x 2 Da Db x 128 on the edge pairs (Da, Db: the hulls' most edges at a vertex, 9-15 on robot arms'
#: hulls capped at 64 vertices), 0.1-0.2 M dot products per substep, each a statement of a generated kernel.
#: Measured, eager, batch 1, float64, 2 shared cores: a step of robosuite's Panda, UR5e, xArm7 (16-22 mesh pairs,
#: hulls capped at 64) takes 37-61 ms, TIAGo's (266 mesh pairs) 1.1 s. The robot models of dm_control, robosuite and gymnasium-robotics have
#: hulls of 100-10600 vertices (median 232 over their colliding meshes); MuJoCo's ``maxhullvert`` caps a hull at
#: compile time, and with it MuJoCo and torchsim collide the same hull (``load_mjcf(max_hull_vertices=64)`` sets it
#: on every colliding mesh that needs it: ``torchsim.io_mjcf.hull_caps``).
MAX_HULL_VERTICES = 64


def hull_fields(m: mujoco.MjModel, geoms) -> dict:
    """The convex hulls of the mesh geoms among ``geoms`` (those that can collide) in their geom frames:
    ``geom_hull_vert (G, V, 3)`` [m], ``geom_hull_real (G, V)`` (false at padding), ``geom_hull_edge (G, V, D, 3)``
    [m] the edges from each vertex to its ``D`` neighbours on the hull (padded by repeating the first) and
    ``geom_hull_plane (G, F, 4)`` (outward unit normal and offset [m]: a point ``x`` is inside where
    ``n . x <= offset`` for every plane), ``V``, ``D`` and ``F`` the model's largest (0 without colliding meshes).
    Refuses a hull of more than ``MAX_HULL_VERTICES`` vertices by name."""
    hulls = {g: _hull(m, g) for g in sorted(set(geoms)) if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH}
    nvert = max((len(v) for v, _, _ in hulls.values()), default=0)
    ndeg = max((len(row) for _, e, _ in hulls.values() for row in e), default=0)
    nplane = max((len(p) for _, _, p in hulls.values()), default=0)
    vert, real = np.zeros((m.ngeom, nvert, 3)), np.zeros((m.ngeom, nvert), bool)
    edge, plane = np.zeros((m.ngeom, nvert, ndeg, 3)), np.zeros((m.ngeom, nplane, 4))
    for g, (v, e, p) in hulls.items():
        vert[g], real[g, :len(v)], plane[g] = _padded(v, nvert), True, _padded(p, nplane)
        edge[g] = _padded(np.stack([_padded(row, ndeg) for row in e]), nvert)
    return dict(geom_hull_vert=torch.as_tensor(vert), geom_hull_real=torch.as_tensor(real),
                geom_hull_edge=torch.as_tensor(edge), geom_hull_plane=torch.as_tensor(plane))


def _padded(rows: np.ndarray, n: int) -> np.ndarray:
    """``rows``, then its first row repeated up to ``n`` rows."""
    return rows[np.where(np.arange(n) < len(rows), np.arange(n), 0)]


def _hull(m: mujoco.MjModel, g: int) -> tuple[np.ndarray, list, np.ndarray]:
    """Mesh geom ``g``'s hull: vertices ``(n, 3)``, each one's edges to its neighbours (``n`` arrays ``(k, 3)``;
    only edges between faces of different planes) and merged face planes ``(f, 4)``, geom frame."""
    mesh = m.geom_dataid[g]
    verts = m.mesh_vert[m.mesh_vertadr[mesh]:m.mesh_vertadr[mesh] + m.mesh_vertnum[mesh]].astype(np.float64)
    adr = m.mesh_graphadr[mesh]
    if adr < 0:
        raise UnsupportedMJCFError(f"mesh geom {name(m, mujoco.mjtObj.mjOBJ_GEOM, g)!r} can collide and MuJoCo "
                                   "compiled no convex hull for its mesh")
    numvert, numface = m.mesh_graph[adr:adr + 2]
    ids = m.mesh_graph[adr + 2 + numvert:adr + 2 + 2 * numvert]
    start = adr + 2 + 3 * numvert + 3 * numface
    triangles = m.mesh_graph[start:start + 3 * numface].reshape(-1, 3)
    if len(ids) > MAX_HULL_VERTICES:
        mesh_name = name(m, mujoco.mjtObj.mjOBJ_MESH, mesh)
        raise UnsupportedMJCFError(
            f"mesh geom {name(m, mujoco.mjtObj.mjOBJ_GEOM, g)!r} can collide and its convex hull has {len(ids)} "
            f"vertices, more than the {MAX_HULL_VERTICES} torchsim collides; cap the colliding meshes' hulls with "
            f"load_mjcf(..., max_hull_vertices={MAX_HULL_VERTICES}), or this one's with <mesh name={mesh_name!r} "
            f"maxhullvert=\"{MAX_HULL_VERTICES}\"> (MuJoCo's cap: MuJoCo then collides that hull too)")
    planes, plane_of = _planes(verts, triangles, verts[ids].mean(0))
    # the hull's edges: between triangles of two planes (a diagonal inside a merged face is none)
    sides = {}
    for tri, plane in zip(triangles.tolist(), plane_of):
        for k in range(3):
            sides.setdefault(frozenset((tri[k], tri[k - 1])), set()).add(plane)
    neighbours = {int(i): [] for i in ids}
    for edge, faces in sides.items():
        if len(faces) > 1:
            i, j = edge
            neighbours[i].append(j)
            neighbours[j].append(i)
    # a vertex inside a merged face (within its tolerance) has none: a zero edge, which gives no axis
    edges = [verts[sorted(neighbours[int(i)])] - verts[i] if neighbours[int(i)] else np.zeros((1, 3)) for i in ids]
    return verts[ids], edges, planes


def _planes(verts: np.ndarray, triangles: np.ndarray, inside: np.ndarray) -> tuple[np.ndarray, list]:
    """Outward planes ``(f, 4)`` of a hull's triangles, coplanar ones (normals and offsets equal within the float32
    precision MuJoCo keeps mesh vertices in) merged, and each triangle's plane; ``inside``: a point inside the
    hull."""
    a, b, c = (verts[triangles[:, i]] for i in range(3))
    normal = np.cross(b - a, c - a)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    offset = (normal * a).sum(1)
    flip = np.where((normal * inside).sum(1) > offset, -1.0, 1.0)[:, None]  # the inside point must be below
    planes = np.concatenate([normal, offset[:, None]], 1) * flip
    scale = np.abs(verts).max()
    tolerance = np.array([1e-5, 1e-5, 1e-5, 1e-5 * scale])
    # greedy in triangle order: a triangle joins the first merged plane it matches, else starts one. The first
    # triangle left unassigned starts the next plane, which takes every unassigned triangle that matches it
    # (one pass per merged plane, not per pair of triangles)
    match = (np.abs(planes[:, None] - planes[None]) <= tolerance).all(-1)  # (t, t)
    plane_of = np.full(len(planes), -1)
    first = []
    while (plane_of < 0).any():
        i = int(np.argmax(plane_of < 0))
        plane_of[(plane_of < 0) & match[i]] = len(first)
        plane_of[i] = len(first)  # a degenerate (NaN) plane matches nothing, itself included
        first.append(i)
    return planes[first], plane_of.tolist()
