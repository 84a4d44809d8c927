"""MuJoCo ``<sensor>`` elements -> torchsim sensors: each sensor's type, object, reference frame and place in
MuJoCo's ``sensordata``, grouped by type for ``torchsim.sensors``.

Sensors read the State: joint, tendon and actuator positions and velocities, frame poses and velocities of bodies,
geoms, sites and (fixed) cameras, subtree centres of mass, their velocities and angular momenta, gyros,
velocimeters and magnetometers, joint and tendon limits, potential and kinetic energy, and, given the controls,
actuator forces, touch (``torchsim.contact_forces``) and the sensors read over the next step: accelerations
(``accelerometer``, ``framelinacc``, ``frameangacc``, the mean over the step where MuJoCo reads the instantaneous
value) and the wrench a body's parent puts on its subtree (``force``, ``torque``; refused, with the reason, where
forces MuJoCo counts as external act on the subtree that torchsim does not read out: connect and weld constraints,
the contacts of a body fused with its parent when both sides' geoms collide, a body fixed to the world; and, where
the model has contacts, a method other than spring, whose contact forces are not read out). Sensors
that need other constraint forces (``contact``, ``jointlimitfrc``, ...), the simulation time (``clock``) or a
history (``delay``, ``interval``), and those not implemented yet (``rangefinder``, ``camprojection``,
``insidesite``, ``distance``, ``normal``, ``fromto``; :data:`WHY`), are kept in the layout but not computed: one
warning names them, their ``sensordata`` slots read NaN and reading one by name raises. ``cutoff`` clamps as in
MuJoCo; ``noise`` is ignored, as MuJoCo's engine ignores it (the model only stores it).
"""

import warnings
from collections import defaultdict
from typing import NamedTuple

import mujoco
import numpy as np
import torch

from torchsim.io_mjcf.bodies import FusedBodies, compose
from torchsim.io_mjcf.subset import name
from torchsim.system import SensorGroup

Obj = mujoco.mjtObj
Sens = mujoco.mjtSensor

#: MJCF element name of each sensor type (``mjtSensor``), for the names users read and the warning.
KIND = {int(t): n for t, n in {
    Sens.mjSENS_JOINTPOS: "jointpos", Sens.mjSENS_JOINTVEL: "jointvel", Sens.mjSENS_BALLQUAT: "ballquat",
    Sens.mjSENS_BALLANGVEL: "ballangvel", Sens.mjSENS_TENDONPOS: "tendonpos", Sens.mjSENS_TENDONVEL: "tendonvel",
    Sens.mjSENS_ACTUATORPOS: "actuatorpos", Sens.mjSENS_ACTUATORVEL: "actuatorvel",
    Sens.mjSENS_ACTUATORFRC: "actuatorfrc", Sens.mjSENS_JOINTACTFRC: "jointactuatorfrc",
    Sens.mjSENS_TENDONACTFRC: "tendonactuatorfrc", Sens.mjSENS_FRAMEPOS: "framepos",
    Sens.mjSENS_FRAMEQUAT: "framequat", Sens.mjSENS_FRAMEXAXIS: "framexaxis", Sens.mjSENS_FRAMEYAXIS: "frameyaxis",
    Sens.mjSENS_FRAMEZAXIS: "framezaxis", Sens.mjSENS_FRAMELINVEL: "framelinvel",
    Sens.mjSENS_FRAMEANGVEL: "frameangvel", Sens.mjSENS_SUBTREECOM: "subtreecom",
    Sens.mjSENS_SUBTREELINVEL: "subtreelinvel", Sens.mjSENS_SUBTREEANGMOM: "subtreeangmom",
    Sens.mjSENS_GYRO: "gyro", Sens.mjSENS_VELOCIMETER: "velocimeter",
    Sens.mjSENS_MAGNETOMETER: "magnetometer", Sens.mjSENS_JOINTLIMITPOS: "jointlimitpos",
    Sens.mjSENS_JOINTLIMITVEL: "jointlimitvel", Sens.mjSENS_TENDONLIMITPOS: "tendonlimitpos",
    Sens.mjSENS_TENDONLIMITVEL: "tendonlimitvel", Sens.mjSENS_E_POTENTIAL: "e_potential",
    Sens.mjSENS_E_KINETIC: "e_kinetic", Sens.mjSENS_TOUCH: "touch", Sens.mjSENS_ACCELEROMETER: "accelerometer",
    Sens.mjSENS_FRAMELINACC: "framelinacc", Sens.mjSENS_FRAMEANGACC: "frameangacc", Sens.mjSENS_FORCE: "force",
    Sens.mjSENS_TORQUE: "torque",
}.items()}
#: MJCF names of types not computed whose enum name differs.
ELEMENT = {int(Sens.mjSENS_GEOMDIST): "distance", int(Sens.mjSENS_GEOMNORMAL): "normal",
           int(Sens.mjSENS_GEOMFROMTO): "fromto"}
#: The computed kinds by what their group's ``obj`` indexes (``System.sensor_groups``); the other computed kinds
#: (tendon and actuator sensors) index tendons and actuators, whose order is MuJoCo's.
QPOS_KINDS, QVEL_KINDS = ("jointpos", "ballquat"), ("jointvel", "ballangvel")
DOF_KINDS = ("jointactuatorfrc", "jointlimitpos", "jointlimitvel")
FRAME_KINDS = ("framepos", "framequat", "framexaxis", "frameyaxis", "framezaxis", "framelinvel", "frameangvel",
               "gyro", "velocimeter", "magnetometer")
SUBTREE_KINDS = ("subtreecom", "subtreelinvel", "subtreeangmom")
LIMIT_KINDS = ("jointlimitpos", "jointlimitvel", "tendonlimitpos", "tendonlimitvel")
ENERGY_KINDS = ("e_potential", "e_kinetic")
ACTUATOR_KINDS = ("actuatorpos", "actuatorvel", "actuatorfrc", "jointactuatorfrc", "tendonactuatorfrc")
#: The kinds read from the accelerations over the next step: their group's ``obj`` is the sensor frame of their object
#: (a site for ``accelerometer``); and the kinds read from the wrench the parent puts on a site's body's subtree: their
#: ``obj`` is the site's sensor frame and their ``ref`` the subtree's row (``System.sensor_subtree_*``).
ACC_KINDS = ("accelerometer", "framelinacc", "frameangacc")
WRENCH_KINDS = ("force", "torque")
#: A touch sensor's site shape (``mjtGeom``) -> its code in ``torchsim.render.raycast.CODE`` (the ray tests).
TOUCH_SHAPES = {int(mujoco.mjtGeom.mjGEOM_SPHERE): 1, int(mujoco.mjtGeom.mjGEOM_CAPSULE): 2,
                int(mujoco.mjtGeom.mjGEOM_ELLIPSOID): 3, int(mujoco.mjtGeom.mjGEOM_CYLINDER): 4,
                int(mujoco.mjtGeom.mjGEOM_BOX): 5}
#: The MjModel field prefix of each object type frame sensors read besides bodies.
PREFIX = {int(Obj.mjOBJ_GEOM): "geom", int(Obj.mjOBJ_SITE): "site", int(Obj.mjOBJ_CAMERA): "cam"}
#: Why the other sensor types are not computed.
_FORCES = "it needs contact or constraint forces, which the State does not hold"
_NOT_YET = "it is not implemented yet (the State holds what it needs)"
WHY = {int(t): why for t, why in {
    Sens.mjSENS_CONTACT: _FORCES, Sens.mjSENS_TACTILE: _FORCES,
    Sens.mjSENS_JOINTLIMITFRC: _FORCES, Sens.mjSENS_TENDONLIMITFRC: _FORCES,
    Sens.mjSENS_CAMPROJECTION: _NOT_YET, Sens.mjSENS_INSIDESITE: _NOT_YET,
    Sens.mjSENS_GEOMDIST: _NOT_YET, Sens.mjSENS_GEOMNORMAL: _NOT_YET, Sens.mjSENS_GEOMFROMTO: _NOT_YET,
    Sens.mjSENS_RANGEFINDER: "it is not implemented yet (ray casts against the geoms)",
    Sens.mjSENS_CLOCK: "it needs the simulation time, which the State does not hold",
    Sens.mjSENS_USER: "it is user code", Sens.mjSENS_PLUGIN: "it is a plugin",
}.items()}


class _FrameTable:
    """The frames sensors read, each once: ``(ext body, position from its COM and orientation in its frame)``;
    frame 0 is the world's (the reference of sensors without one)."""

    def __init__(self, world: int):
        self.rows = [(world, np.zeros(3), np.array([1.0, 0, 0, 0]))]
        self.index = {}

    def add(self, key, body: int, pos: np.ndarray, quat: np.ndarray) -> int:
        if key not in self.index:
            self.index[key] = len(self.rows)
            self.rows.append((body, pos, quat))
        return self.index[key]


def sensor_fields(m: mujoco.MjModel, fused: FusedBodies, jnt_dof: dict) -> dict:
    """The System's sensor fields (``System`` documents them); ``jnt_dof``: MuJoCo joint id -> torchsim dof."""
    frames = _FrameTable(fused.index[0])
    subtrees = {}  # MuJoCo body -> subtree row
    touch_zones = []  # (site size, shape code) of each touch sensor
    groups = defaultdict(list)  # kind -> [(adr, obj, ref)]
    skipped = []
    for i in range(m.nsensor):
        kind = KIND.get(int(m.sensor_type[i]))
        why = _not_computed(m, i, kind)
        if why:
            skipped.append(why)
            continue
        skipped.append("")
        obj_type, obj, ref_type, ref = (int(x) for x in (m.sensor_objtype[i], m.sensor_objid[i],
                                                          m.sensor_reftype[i], m.sensor_refid[i]))
        if kind in FRAME_KINDS:
            row = (_frame(m, fused, frames, obj_type, obj), _frame(m, fused, frames, ref_type, ref) if ref >= 0 else 0)
        elif kind in QPOS_KINDS:
            row = (m.jnt_qposadr[obj], -1)
        elif kind in QVEL_KINDS:
            row = (m.jnt_dofadr[obj], -1)
        elif kind in DOF_KINDS:
            row = (jnt_dof[obj], -1)
        elif kind in SUBTREE_KINDS:
            row = (subtrees.setdefault(obj, len(subtrees)), -1)
        elif kind == "touch":  # its site's frame and its row of the touch zones
            row = (_frame(m, fused, frames, obj_type, obj), len(touch_zones))
            touch_zones.append((m.site_size[obj].copy(), TOUCH_SHAPES[int(m.site_type[obj])]))
        elif kind in ACC_KINDS:  # its object's frame
            row = (_frame(m, fused, frames, obj_type, obj), -1)
        elif kind in WRENCH_KINDS:  # its site's frame and the row of the subtree of the site's body
            row = (_frame(m, fused, frames, obj_type, obj), subtrees.setdefault(int(m.site_bodyid[obj]), len(subtrees)))
        elif kind in ENERGY_KINDS:  # the whole model's
            row = (0, -1)
        else:  # a tendon or actuator sensor
            row = (obj, -1)
        groups[kind].append((m.sensor_adr[i], *row))
    kinds = tuple(KIND.get(int(t), ELEMENT.get(int(t), mujoco.mjtSensor(t).name.removeprefix("mjSENS_").lower()))
                  for t in m.sensor_type)
    _warn_skipped(m, kinds, skipped)
    terms = _subtree_terms(m, fused, frames, subtrees)
    cutoff = np.full(m.nsensordata, np.inf)
    for i in range(m.nsensor):
        if m.sensor_cutoff[i] > 0 and m.sensor_datatype[i] == int(mujoco.mjtDataType.mjDATATYPE_REAL):
            cutoff[m.sensor_adr[i]:m.sensor_adr[i] + m.sensor_dim[i]] = m.sensor_cutoff[i]
    body, pos, quat = zip(*frames.rows)
    return dict(
        nsensordata=int(m.nsensordata),
        sensor_names=tuple(name(m, Obj.mjOBJ_SENSOR, i) for i in range(m.nsensor)), sensor_kinds=kinds,
        sensor_adr=tuple(int(a) for a in m.sensor_adr), sensor_dims=tuple(int(d) for d in m.sensor_dim),
        sensor_skipped=tuple(skipped),
        sensor_groups=tuple(SensorGroup(kind, *(torch.as_tensor(np.array([r[k] for r in rows], dtype=np.int64))
                                                for k in range(3)))
                            for kind, rows in sorted(groups.items())),
        sensor_frame_body=torch.as_tensor(np.array(body, dtype=np.int64)),
        sensor_frame_pos=torch.as_tensor(np.array(pos)), sensor_frame_quat=torch.as_tensor(np.array(quat)),
        sensor_subtree_row=torch.as_tensor(np.array([t.row for t in terms], dtype=np.int64)),
        sensor_subtree_frame=torch.as_tensor(np.array([t.frame for t in terms], dtype=np.int64)),
        sensor_subtree_mass=torch.as_tensor(np.array([t.mass for t in terms], dtype=float)),
        sensor_subtree_inertia=torch.as_tensor(np.array([t.inertia for t in terms], dtype=float).reshape(-1, 3)),
        sensor_magnetic=torch.as_tensor(m.opt.magnetic.copy()), sensor_cutoff=torch.as_tensor(cutoff),
        sensor_static_potential=torch.tensor(_static_potential(m, fused), dtype=torch.float64),
        sensor_touch_size=torch.as_tensor(np.array([z[0] for z in touch_zones], dtype=float).reshape(-1, 3)),
        sensor_touch_shape=torch.as_tensor(np.array([z[1] for z in touch_zones], dtype=np.int64)),
        sensor_subtree_contact=torch.as_tensor(_subtree_contacts(m, fused, subtrees)),
    )


def _not_computed(m: mujoco.MjModel, i: int, kind: str | None) -> str:
    """Why sensor ``i`` is not computed ("" if it is)."""
    if m.sensor_delay[i] > 0 or m.sensor_interval[i, 0] > 0:
        return "its delay or interval needs a history of states"
    if kind is None:
        return WHY.get(int(m.sensor_type[i]), "it is not implemented")
    obj_type, obj = int(m.sensor_objtype[i]), int(m.sensor_objid[i])
    if kind in FRAME_KINDS or kind == "touch" or kind in ACC_KINDS:
        objects = [(obj_type, obj)]
        if kind in FRAME_KINDS and m.sensor_refid[i] >= 0:  # a frame sensor may be relative to another object
            objects.append((int(m.sensor_reftype[i]), int(m.sensor_refid[i])))
        if any(t == Obj.mjOBJ_CAMERA and m.cam_mode[o] != int(mujoco.mjtCamLight.mjCAMLIGHT_FIXED)
               for t, o in objects):
            return "its camera is not fixed to its body (mode)"
        bodies = [_body(m, t, o) for t, o in objects]
    elif kind in WRENCH_KINDS:
        bodies = _subtree_bodies(m, int(m.site_bodyid[obj]))
        why = _wrench_not_computed(m, int(m.site_bodyid[obj]))
        if why:
            return why
    else:
        bodies = _subtree_bodies(m, obj) if kind in SUBTREE_KINDS else []
    if any(m.body_mocapid[b] >= 0 for b in bodies):  # fused into the world, they would read the model's pose
        return "it reads a mocap body, whose pose is a System parameter (sys.mocap_pos, sys.mocap_quat)"
    if kind in ACTUATOR_KINDS and np.any(m.actuator_trntype == int(mujoco.mjtTrn.mjTRN_SITE)):
        return "actuators with site transmission are not read by sensors yet"
    if kind == "jointactuatorfrc" and (m.jnt_actfrclimited[obj] or m.jnt_actgravcomp[obj]):
        return "its joint's actuatorfrcrange or actuatorgravcomp is not modelled"
    if kind == "jointactuatorfrc" and any(
            m.actuator_trntype[a] == int(mujoco.mjtTrn.mjTRN_TENDON)
            and m.wrap_type[m.tendon_adr[m.actuator_trnid[a, 0]]] != int(mujoco.mjtWrap.mjWRAP_JOINT)
            for a in range(m.nu)):
        return "an actuator acts on a spatial tendon, whose force torchsim applies to bodies, not to dofs"
    if kind in ("jointlimitpos", "jointlimitvel") and int(m.jnt_type[obj]) not in (int(mujoco.mjtJoint.mjJNT_HINGE),
                                                                                    int(mujoco.mjtJoint.mjJNT_SLIDE)):
        return "limits of free and ball joints are not modelled"
    if kind in LIMIT_KINDS and m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_LIMIT):
        return "limits are disabled (<flag limit>), which torchsim does not model"
    if kind in SUBTREE_KINDS and _subtree_mass(m, obj) < mujoco.mjMINVAL:
        return "its subtree has no mass"
    if kind == "e_potential":
        springs = np.any(m.jnt_stiffness != 0) or np.any(m.tendon_stiffness != 0)
        if springs and m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_SPRING):
            return "springs are disabled (<flag spring>), which torchsim does not model"
        if np.any(m.jnt_stiffnesspoly != 0):
            return "polynomial joint stiffness is not modelled"
        if any(m.body_mass[b] > 0 for b in range(1, m.nbody) if m.body_mocapid[m.body_weldid[b]] >= 0):
            return "it weighs mocap bodies, whose poses are System parameters"
    return ""


def _collides(m: mujoco.MjModel) -> np.ndarray:
    """Whether each geom can take part in a contact: ``contype``/``conaffinity`` bits or an explicit ``<pair>``."""
    collides = (m.geom_contype != 0) | (m.geom_conaffinity != 0)
    collides[m.pair_geom1] = True
    collides[m.pair_geom2] = True
    return collides


def _wrench_not_computed(m: mujoco.MjModel, body: int) -> str:
    """Why a force or torque sensor on MuJoCo body ``body`` is not computed ("" if it is): MuJoCo's ``cfrc_int``
    subtracts from the subtree's inertial wrench every force it counts as external (``cfrc_ext``: contacts,
    connect and weld constraints, ``xfrc_applied``); torchsim must subtract the same ones, from the contact forces
    it reads out (``torchsim.contact_forces``), or refuse."""
    if m.body_weldid[body] == 0:
        return ("its site's body is fixed to the world, whose contacts torchsim's contact forces do not tell apart "
                "from the world's")
    inside = set(_subtree_bodies(m, body))
    for e in range(m.neq):
        if int(m.eq_type[e]) in (int(mujoco.mjtEq.mjEQ_CONNECT), int(mujoco.mjtEq.mjEQ_WELD)):
            ends = (m.eq_obj1id[e], m.eq_obj2id[e])
            if m.eq_objtype[e] == Obj.mjOBJ_SITE:
                ends = tuple(m.site_bodyid[s] for s in ends)
            if any(int(b) in inside for b in ends):
                return ("a connect or weld constraint pulls on its subtree: MuJoCo counts that force as external, "
                        "which torchsim does not read out")
    same = [b for b in range(m.nbody) if m.body_weldid[b] == m.body_weldid[body]]  # fused into one torchsim body
    collides = _collides(m)
    sides = {b in inside for b in same for g in range(m.body_geomadr[b], m.body_geomadr[b] + m.body_geomnum[b])
             if collides[g]}
    if len(sides) == 2:
        return ("its body has no joint to its parent and geoms on both sides of it collide: the contact forces on "
                "their fused torchsim body do not say which side they push")
    return ""


def _subtree_contacts(m: mujoco.MjModel, fused: FusedBodies, subtrees: dict) -> np.ndarray:
    """``(R, N + 1)``: 1 where the contacts of torchsim body ``n`` (``N``: the world) push on subtree row ``r``:
    the body holds MuJoCo bodies of the subtree and no colliding geom outside it (force and torque sensors are
    refused where it holds colliding geoms on both sides, :func:`_wrench_not_computed`)."""
    n = len(fused.roots)
    weights = np.zeros((len(subtrees), n + 1))
    collides = _collides(m)
    for root, row in subtrees.items():
        inside = set(_subtree_bodies(m, root))
        for b in inside:
            if m.body_weldid[b] != 0 and m.body_mocapid[b] < 0:
                weights[row, fused.body_of(m, b)] = 1.0
        for b in range(m.nbody):  # a colliding geom outside the subtree on a body fused with one inside it
            geoms = range(m.body_geomadr[b], m.body_geomadr[b] + m.body_geomnum[b])
            if b not in inside and m.body_weldid[b] != 0 and any(collides[g] for g in geoms):
                weights[row, fused.body_of(m, b)] = 0.0
    return weights


def _static_potential(m: mujoco.MjModel, fused: FusedBodies) -> float:
    """The gravitational potential energy [J] of the bodies fused into the world, ``-m g . x`` at their COMs
    (MuJoCo's ``e_potential`` counts every body; the System keeps no mass for these)."""
    if m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_GRAVITY):
        return 0.0
    static = [b for b in range(1, m.nbody) if m.body_weldid[b] == 0]
    coms = [compose(*fused.frame[b], m.body_ipos[b], m.body_iquat[b])[0] for b in static]
    return float(-sum(m.body_mass[b] * m.opt.gravity @ com for b, com in zip(static, coms)))


def _warn_skipped(m: mujoco.MjModel, kinds: tuple, skipped: list) -> None:
    by_kind = defaultdict(list)
    for i, why in enumerate(skipped):
        if why:
            by_kind[f"{kinds[i]} ({why})"].append(repr(name(m, Obj.mjOBJ_SENSOR, i)))
    if by_kind:
        listed = "; ".join(f"{kind}: {', '.join(names)}" for kind, names in by_kind.items())
        warnings.warn(f"sensors not computed by torchsim (their sensordata reads NaN, reading one by name raises): "
                      f"{listed}", stacklevel=4)


def _frame(m: mujoco.MjModel, fused: FusedBodies, frames: _FrameTable, obj_type: int, obj: int) -> int:
    """The frame index of object ``obj`` of type ``obj_type``: MuJoCo's ``mjOBJ_BODY`` is the body's inertial
    frame (``xipos``, ``ximat``), ``mjOBJ_XBODY`` its frame (``xpos``, ``xmat``); geoms, sites and cameras theirs."""
    if obj_type == Obj.mjOBJ_BODY:
        local = (m.body_ipos[obj], m.body_iquat[obj])
    elif obj_type == Obj.mjOBJ_XBODY:
        local = (np.zeros(3), np.array([1.0, 0, 0, 0]))
    else:
        local = (getattr(m, f"{PREFIX[obj_type]}_pos")[obj], getattr(m, f"{PREFIX[obj_type]}_quat")[obj])
    body = _body(m, obj_type, obj)
    pos, quat = compose(*fused.frame[body], *local)
    return frames.add((obj_type, obj), fused.body_of(m, body), pos - fused.com_of(m, body), quat)


def _body(m: mujoco.MjModel, obj_type: int, obj: int) -> int:
    """The MuJoCo body that object ``obj`` of type ``obj_type`` (a frame sensor's object or reference) moves with."""
    return obj if obj_type in (Obj.mjOBJ_BODY, Obj.mjOBJ_XBODY) else int(getattr(m, f"{PREFIX[obj_type]}_bodyid")[obj])


def _subtree_bodies(m: mujoco.MjModel, root: int) -> list:
    """MuJoCo body ``root`` and its descendants (MuJoCo numbers a parent before its children)."""
    inside = {root}
    for b in range(root + 1, m.nbody):
        if m.body_parentid[b] in inside:
            inside.add(b)
    return sorted(inside)


def _subtree_mass(m: mujoco.MjModel, root: int) -> float:
    return float(m.body_mass[_subtree_bodies(m, root)].sum())


class _Term(NamedTuple):
    row: int
    frame: int
    mass: float
    inertia: np.ndarray


def _subtree_terms(m: mujoco.MjModel, fused: FusedBodies, frames: _FrameTable, subtrees: dict) -> list:
    """Each subtree row as terms ``(row, frame, mass, inertia)``: one per MuJoCo body of the subtree with mass, at
    its inertial frame (its COM and principal axes), with its principal moments of inertia."""
    return [_Term(row, _frame(m, fused, frames, Obj.mjOBJ_BODY, b), float(m.body_mass[b]), m.body_inertia[b])
            for root, row in subtrees.items() for b in _subtree_bodies(m, root) if m.body_mass[b] > 0]
