"""The static half of a rendered scene, built once per model and shared by every env of a batch.

A :class:`Scene` holds what the camera can see that never changes between envs or steps: each visible geom's
shape type, size, colour, pose relative to the frame it rides on, and the model's cameras and clip distances. Per
env only the frames' poses change: the bodies' (``State.x_pos``, ``State.x_quat``) and the mocap bodies'
(``System.mocap_pos``, ``mocap_quat``, which may be set per env); :func:`torchsim.render.render` combines the two.

Frames are indexed as ``System.geom_frame`` indexes them: the ``N`` torchsim bodies, the static world (``N``), then
the ``M`` mocap bodies (``N + 1 + k``, MuJoCo's ``body_mocapid`` order): a geom or camera on a mocap body, or on a
jointless body fused into one, rides on that mocap frame, so it is drawn where each env's mocap pose puts it.

Geoms are taken from the ``mujoco.MjModel`` rather than from the ``System``, so visual-only geoms
(``contype = conaffinity = 0``) are included; their MuJoCo body is mapped to the torchsim body it is fused into
through ``System.mjbody_*``. Visibility follows what ``mujoco.Renderer`` shows with its default options: geom groups
0-2, and geoms whose colour (``rgba``, or the material's where the geom's ``rgba`` is MuJoCo's default) is not fully
transparent. Mesh geoms are drawn as their triangle meshes, through a bounding-volume hierarchy per mesh asset built
here (:mod:`torchsim.render.mesh`); height fields are triangulated here as MuJoCo's renderer draws them (surface,
side walls and bottom: :mod:`torchsim.render.hfield`) and drawn the same way.
"""

import dataclasses

import mujoco
import numpy as np
import torch

from torchsim.render.camera import Camera, cameras_from_model
from torchsim.render.frames import quat_to_mat_np
from torchsim.render.mesh import Meshes
from torchsim.render import hfield as hfield_mesh
from torchsim.render import mesh as mesh_bvh

#: Geom types the renderer intersects in closed form, by MuJoCo ``mjtGeom`` value.
SHAPES = {
    int(mujoco.mjtGeom.mjGEOM_PLANE): "plane", int(mujoco.mjtGeom.mjGEOM_SPHERE): "sphere",
    int(mujoco.mjtGeom.mjGEOM_CAPSULE): "capsule", int(mujoco.mjtGeom.mjGEOM_ELLIPSOID): "ellipsoid",
    int(mujoco.mjtGeom.mjGEOM_CYLINDER): "cylinder", int(mujoco.mjtGeom.mjGEOM_BOX): "box",
}
#: Mesh geoms: triangle meshes (:mod:`torchsim.render.mesh`), drawn besides the closed-form shapes.
MESH = int(mujoco.mjtGeom.mjGEOM_MESH)
#: Height-field geoms: triangulated at scene build (:mod:`torchsim.render.hfield`) and drawn as meshes.
HFIELD = int(mujoco.mjtGeom.mjGEOM_HFIELD)
#: Geom types drawn through a BVH of triangles (the ``"mesh"`` group of ``Scene.groups``).
TRIANGLES = ("mesh", "hfield")
#: MuJoCo's default geom colour: a geom with a material and this rgba shows the material's colour.
DEFAULT_RGBA = np.array([0.5, 0.5, 0.5, 1.0])


class UnsupportedGeomError(ValueError):
    """A visible geom has a type the renderer cannot intersect (sdf)."""


@dataclasses.dataclass(frozen=True)
class Scene:
    """Static description of what cameras see. ``G`` rendered geoms, ``N`` torchsim bodies (ext index ``N``: the
    world), ``M`` MuJoCo bodies, ``K`` mocap bodies (frames ``N + 1 + k``: the module docstring).

    Attributes:
        geom_id: (G,) MuJoCo geom id of each rendered geom (what segmentation images hold).
        geom_type: (G,) shape names (``SHAPES`` values, ``"mesh"`` or ``"hfield"``).
        geom_body: (G,) frame carrying the geom: a torchsim body's ext index, the world's (``N``), or a mocap
            body's (``N + 1 + k``).
        geom_pos, geom_rot: (G, 3), (G, 3, 3) the geom's frame in its carrier's frame (the body COM frame of
            ``State.x_pos``/``x_quat``; the world frame for static geoms; the mocap body's frame).
        geom_size: (G, 3) MuJoCo sizes.  geom_rgba: (G, 4) colour as MuJoCo's renderer uses it.
        geom_radius: (G,) radius of a sphere about the geom's centre that holds it (inf: infinite planes).
        geom_mesh: (G,) index into ``meshes`` of each mesh or hfield geom's triangles (-1: neither).
        meshes: the BVHs of the mesh assets and triangulated height fields the rendered geoms use
            (:class:`torchsim.render.mesh.Meshes`; None without mesh or hfield geoms).
        groups: ``(shape name, (g,) positions into the G geoms)`` per shape type present (mesh and hfield geoms
            together in ``"mesh"``: both are cast through their BVH).
        cameras: the model's ``<camera>`` elements (:class:`Camera`; may be empty).
        znear, zfar: clip distances [m], MuJoCo's ``vis.map.znear/zfar`` times ``stat.extent``; nothing nearer or
            farther is drawn, and empty pixels have depth ``zfar`` (as MuJoCo's depth buffer).
        num_bodies: ``N``.  mjbody_body: (M,) frame each MuJoCo body rides on (as ``geom_body``); mjbody_pos,
            mjbody_rot: (M, 3), (M, 3, 3) the MuJoCo body's frame in it.  mjbody_names: (M,) names.
        mocap_pos, mocap_quat: (K, 3), (K, 4) the mocap bodies' model poses in the world (the System's at load),
            where :func:`torchsim.render.render` draws them unless given per-env poses.
        skipped: names of geoms left out because their type is unsupported (``skip_unsupported=True``: SDFs).
        unsupported_cameras: ``(name, reason)`` of model cameras left out of ``cameras`` (modes other than fixed
            and track, orthographic or intrinsics cameras); selecting one by name raises with the reason.
    """

    geom_id: torch.Tensor
    geom_type: tuple
    geom_body: torch.Tensor
    geom_pos: torch.Tensor
    geom_rot: torch.Tensor
    geom_size: torch.Tensor
    geom_rgba: torch.Tensor
    geom_radius: torch.Tensor
    groups: tuple
    cameras: Camera
    znear: float
    zfar: float
    num_bodies: int
    mjbody_body: torch.Tensor
    mjbody_pos: torch.Tensor
    mjbody_rot: torch.Tensor
    mjbody_names: tuple
    skipped: tuple = ()
    unsupported_cameras: tuple = ()
    geom_mesh: torch.Tensor | None = None
    meshes: Meshes | None = None
    mocap_pos: torch.Tensor = dataclasses.field(default_factory=lambda: torch.zeros(0, 3, dtype=torch.float64))
    mocap_quat: torch.Tensor = dataclasses.field(default_factory=lambda: torch.zeros(0, 4, dtype=torch.float64))

    @staticmethod
    def build(model, system, geom_groups=(0, 1, 2), skip_unsupported: bool = False) -> "Scene":
        """The scene of ``model`` (a ``mujoco.MjModel``, an MJCF path or XML text) as simulated by ``system``
        (the ``torchsim.System`` loaded from the same model; only its body mapping is used).

        Args:
            geom_groups: geom groups drawn (MuJoCo's renderer default: 0, 1, 2).
            skip_unsupported: leave out visible geoms of unsupported types (sdf): they are then invisible in every
                image. Default: raise :class:`UnsupportedGeomError` naming the geom and type.

        Mesh geoms are drawn; their BVHs are built here, once (robosuite's Panda, 50 meshes, 0.13 M triangles: ~0.5 s).
        Height fields are triangulated here, once, from the System's ``hfield_height`` (what it collides; MuJoCo's
        ``hfield_data`` where the System has none): a terrain changed later needs a new Scene.
        """
        m = _model(model)
        nbody = int(system.mjbody_body.shape[0])
        if nbody != m.nbody:
            raise ValueError(f"the System has {nbody} MuJoCo bodies, the model {m.nbody}: not the same model")
        mj_body, mj_pos, mj_rot, mocap_pos, mocap_quat = _mjbody_frames(m, system)
        rows, skipped = [], []
        for g in range(m.ngeom):
            rgba = m.geom_rgba[g].astype(np.float64)
            if m.geom_matid[g] >= 0 and np.allclose(rgba, DEFAULT_RGBA):
                rgba = m.mat_rgba[m.geom_matid[g]].astype(np.float64)
            if m.geom_group[g] not in geom_groups or rgba[3] == 0:
                continue
            kind = SHAPES.get(int(m.geom_type[g]))
            if int(m.geom_type[g]) in (MESH, HFIELD) and m.geom_dataid[g] >= 0:
                kind = "mesh" if int(m.geom_type[g]) == MESH else "hfield"
            if kind is None:
                label = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) or f"#{g}"
                if skip_unsupported:
                    skipped.append(label)
                    continue
                raise UnsupportedGeomError(
                    f"geom {label!r} has type {mujoco.mjtGeom(m.geom_type[g]).name}, which the renderer cannot "
                    "draw (supported: plane, sphere, capsule, ellipsoid, cylinder, box, mesh, hfield); pass "
                    "skip_unsupported=True to leave such geoms out (they are then invisible)")
            b = m.geom_bodyid[g]
            pos = mj_pos[b] + mj_rot[b] @ m.geom_pos[g]
            rot = mj_rot[b] @ quat_to_mat_np(m.geom_quat[g])
            rows.append((g, kind, mj_body[b], pos, rot, m.geom_size[g].astype(np.float64), rgba))
        cameras, refused = cameras_from_model(m, mj_body, mj_pos, mj_rot)
        kinds = tuple(r[1] for r in rows)
        cast = tuple("mesh" if k in TRIANGLES else k for k in kinds)  # mesh and hfield geoms: one BVH group
        groups = tuple((k, torch.as_tensor([i for i, t in enumerate(cast) if t == k], dtype=torch.long))
                       for k in (*SHAPES.values(), "mesh") if k in cast)
        assets = sorted({(r[1], int(m.geom_dataid[r[0]])) for r in rows if r[1] in TRIANGLES})
        meshes = mesh_bvh.build_from([_triangles(m, system, kind, k) for kind, k in assets]) if assets else None
        geom_mesh = [assets.index((r[1], int(m.geom_dataid[r[0]]))) if r[1] in TRIANGLES else -1 for r in rows]
        radius = [mesh_bvh.bounding_radius(meshes, k) if k >= 0 else bounding_radius(r[1], r[5])
                  for r, k in zip(rows, geom_mesh)]
        as_f = lambda i, shape: torch.as_tensor(np.array([r[i] for r in rows], dtype=np.float64).reshape(shape))
        return Scene(
            geom_id=torch.as_tensor([r[0] for r in rows], dtype=torch.long), geom_type=kinds,
            geom_body=torch.as_tensor([r[2] for r in rows], dtype=torch.long),
            geom_pos=as_f(3, (-1, 3)), geom_rot=as_f(4, (-1, 3, 3)), geom_size=as_f(5, (-1, 3)),
            geom_rgba=as_f(6, (-1, 4)),
            geom_radius=torch.as_tensor(radius, dtype=torch.float64),
            groups=groups, cameras=cameras,
            znear=float(m.vis.map.znear * m.stat.extent), zfar=float(m.vis.map.zfar * m.stat.extent),
            num_bodies=int(system.num_bodies), mjbody_body=torch.as_tensor(mj_body, dtype=torch.long),
            mjbody_pos=torch.as_tensor(mj_pos), mjbody_rot=torch.as_tensor(mj_rot),
            mjbody_names=tuple(mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b) or "" for b in range(m.nbody)),
            skipped=tuple(skipped), unsupported_cameras=refused,
            geom_mesh=torch.as_tensor(geom_mesh, dtype=torch.long), meshes=meshes,
            mocap_pos=torch.as_tensor(mocap_pos), mocap_quat=torch.as_tensor(mocap_quat))

    def to(self, device=None, dtype=None) -> "Scene":
        """A copy on ``device`` with floating tensors in ``dtype``."""
        def move(x):
            if isinstance(x, torch.Tensor):
                return x.to(device=device, dtype=dtype if x.is_floating_point() else None)
            if isinstance(x, (Camera, Meshes)):
                return x.to(device, dtype)
            if isinstance(x, tuple) and x and isinstance(x[0], tuple):
                return tuple((k, move(v)) for k, v in x)
            return x
        return dataclasses.replace(self, **{f.name: move(getattr(self, f.name)) for f in dataclasses.fields(self)})

    @property
    def num_geoms(self) -> int:
        return int(self.geom_id.shape[0])

    @property
    def num_mocap(self) -> int:
        return int(self.mocap_pos.shape[0])

    def camera(self, which) -> Camera:
        """Cameras selected by ``which``: a :class:`Camera` (returned as is), a name or index of a model camera,
        or a list of these (concatenated in order)."""
        if isinstance(which, Camera):
            return which
        if isinstance(which, (list, tuple)):
            return Camera.cat([self.camera(w) for w in which])
        if isinstance(which, str):
            reasons = dict(self.unsupported_cameras)
            if which in reasons:
                raise ValueError(f"camera {which!r} cannot be rendered: {reasons[which]}")
            if which not in self.cameras.names:
                raise KeyError(f"no camera named {which!r}; the model's cameras: {list(self.cameras.names)}")
            which = self.cameras.names.index(which)
        if not 0 <= int(which) < self.cameras.num:
            raise IndexError(f"camera index {which} out of range: the model has {self.cameras.num} cameras")
        return self.cameras.select([int(which)])


def _mjbody_frames(m, system):
    """Each MuJoCo body's frame index, position and rotation in that frame (``Scene.mjbody_*``), and the mocap
    bodies' model poses ``(K, 3)``, ``(K, 4)``. The System puts a body riding on a mocap body on the world at the
    mocap body's model pose (it takes no impulse); here it rides on the mocap frame ``N + 1 + k`` instead, posed
    relative to the mocap body."""
    body = system.mjbody_body.cpu().numpy()
    pos = system.mjbody_pos.cpu().double().numpy()
    quat = system.mjbody_quat.cpu().double().numpy()
    rot = np.stack([quat_to_mat_np(q) for q in quat])
    frame, frame_pos, frame_rot = body.copy(), pos.copy(), rot.copy()
    for b in range(m.nbody):
        root = m.body_weldid[b]
        if m.body_mocapid[root] >= 0:  # both at their model poses in the world: b's relative to its root's
            frame[b] = system.num_bodies + 1 + m.body_mocapid[root]
            frame_pos[b], frame_rot[b] = rot[root].T @ (pos[b] - pos[root]), rot[root].T @ rot[b]
    mocap = sorted((b for b in range(m.nbody) if m.body_mocapid[b] >= 0), key=lambda b: m.body_mocapid[b])
    return frame, frame_pos, frame_rot, pos[mocap].reshape(-1, 3), quat[mocap].reshape(-1, 4)


def bounding_radius(kind: str, size) -> float:
    """Radius of the smallest sphere about a geom's centre that holds it (MuJoCo sizes; inf for infinite planes)."""
    if kind == "plane":
        return float(np.hypot(size[0], size[1])) if size[0] > 0 and size[1] > 0 else float("inf")
    radius = {"sphere": size[0], "capsule": size[0] + size[1], "cylinder": np.hypot(size[0], size[1]),
              "ellipsoid": max(size), "box": np.linalg.norm(size)}[kind]
    return float(radius)


def _triangles(m, system, kind: str, k: int):
    """``(name, vertices, triangles)`` of mesh asset ``k`` or of height field ``k``, triangulated."""
    if kind == "mesh":
        return mesh_bvh.mesh_geometry(m, k)
    name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_HFIELD, k) or f"{k}"
    return (f"hfield:{name}", *hfield_mesh.triangulate(hfield_mesh.elevation(m, k, system), m.hfield_size[k]))


def _model(model) -> mujoco.MjModel:
    if isinstance(model, mujoco.MjModel):
        return model
    text = str(model)
    if text.lstrip().startswith("<"):
        return mujoco.MjModel.from_xml_string(text)
    return mujoco.MjModel.from_xml_path(text)
