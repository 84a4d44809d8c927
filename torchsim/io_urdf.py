"""URDF -> :class:`System`, through pytorch-kinematics' URDF parser and the MJCF loader.

Design: the URDF is parsed with pytorch-kinematics' vendored ``urdf_parser_py`` (``pk.URDF``; pk's ``Chain``
drops inertials, collisions and dynamics, the parsed ``Robot`` keeps them), translated into an equivalent MJCF
document (:func:`urdf_to_mjcf`), and that document goes through :func:`torchsim.load_mjcf`, so fusing, joint
grouping, actuators and contact pairs are built in one place. The resulting System's link frames are then
checked against pytorch-kinematics' forward kinematics (``pk.build_chain_from_urdf``) at two configurations,
so a URDF feature the translation gets wrong cannot load silently.

Translation, element by element:
- link -> ``<body>`` placed at its parent joint's ``<origin>``; the root link is fixed to the world (with every
  link hanging from it on fixed joints it is fused into the static world).
- ``<inertial>`` -> ``<inertial pos mass fullinertia>``, the tensor rotated from the inertial frame into the link
  frame. A link without one is massless (``inertiafromgeom="false"``: URDF semantics, no mass from geometry).
- ``fixed`` -> no joint: the loader fuses the child into its parent (mass, COM, inertia combined); massless
  frames such as ``tool0`` stay MuJoCo bodies, so :func:`torchsim.mj_body_poses` returns their poses.
- ``revolute``/``prismatic`` -> ``hinge``/``slide`` with ``range = [lower, upper]``; ``continuous`` -> unlimited
  hinge; ``<dynamics damping>`` -> ``damping``. ``<dynamics friction>`` is dropped with a warning (torchsim has
  no joint friction loss). URDF has no armature: ``armature`` (option) applies to every movable joint.
- every movable joint gets a ``<motor>`` (gear 1) with ``ctrlrange = +-effort``; a missing or zero effort
  leaves it unlimited. Velocity limits are not modelled.
- ``<collision>``: ``box``, ``sphere`` and ``capsule`` (non-standard, accepted by pk's parser and MuJoCo) as they
  are; ``cylinder`` -> capsule of the same radius and half-length, which contains the cylinder (torchsim has
  no cylinder collider). ``<visual>`` is ignored. Contacts follow MuJoCo's defaults: all geoms collide except
  those of a parent and its child.
- ``q``/``qd`` columns and actuators are in pytorch-kinematics' joint order
  (``chain.get_joint_parameter_names()``): depth first, children in document order.

Rejected with :class:`UnsupportedURDFError`: mesh collision geometry (``ignore_meshes=True`` drops it instead;
the link keeps its inertial but touches nothing), ``<mimic>`` joints, ``floating``/``planar`` joints, closed loops
(a link that is the child of two joints), several root links, joints naming unknown links, movable joints without
``<axis>`` (pytorch-kinematics and the URDF spec disagree on the default) or with a zero-length one, and limited joints
with ``lower >= upper``.
"""

import os
import warnings
import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import pytorch_kinematics as pk
import torch
from pytorch_kinematics.urdf_parser_py import urdf as shapes

from torchsim import spatial
from torchsim.io_mjcf import UnsupportedMJCFError, load_mjcf
from torchsim.kinematics import mj_body_poses
from torchsim.pipeline import init
from torchsim.system import System

_MJCF_JOINT = {"revolute": "hinge", "continuous": "hinge", "prismatic": "slide"}
# pk's URDF offsets are float32 (its parser rounds every <origin>), so its float64 FK is off by ~1e-7 per joint;
# a translation error (a wrong frame, axis or sign) shows up at >= 1e-3.
_PK_TOLERANCE = 1e-5


class UnsupportedURDFError(UnsupportedMJCFError):
    """The URDF uses a feature outside torchsim's supported subset (see ``torchsim.io_urdf``)."""


def load_urdf(source, timestep: float = 0.002, armature: float = 0.0, ignore_meshes: bool = False,
              **options) -> System:
    """Load a URDF robot from a file path or the XML text; the root link is fixed to the world.

    Args:
        source: path to a ``.urdf`` file, or the XML text itself.
        timestep: ``System.timestep`` [s] (URDF has none; 2 ms is MuJoCo's default).
        armature: rotor inertia [kg m^2] added to every movable joint (URDF has none).
        ignore_meshes: drop mesh collision geometry instead of raising :class:`UnsupportedURDFError`.
        **options: passed to :func:`torchsim.load_mjcf` (``method``, ``substeps``, ``dtype``, ``device``, ...).
    """
    text = _read(source)
    mjcf, links, joints = _translate(*_parse(text), timestep, armature, ignore_meshes)
    sys = load_mjcf(mjcf, **options)
    _check_against_pk(sys, text, links, joints)
    return sys


def urdf_to_mjcf(source, timestep: float = 0.002, armature: float = 0.0, ignore_meshes: bool = False) -> str:
    """The MJCF text :func:`load_urdf` builds its System from (e.g. to embed the robot in a scene)."""
    return _translate(*_parse(_read(source)), timestep, armature, ignore_meshes)[0]


def _read(source) -> bytes:
    """The URDF as bytes without its ``<mujoco>`` extension element (pk's parser would report it as unknown)."""
    text = str(source)
    if not text.lstrip().startswith("<"):
        if not os.path.isfile(text):
            raise FileNotFoundError(f"URDF file not found: {text}")
        with open(text, encoding="utf-8") as f:
            text = f.read()
    root = ET.fromstring(text)
    if root.tag != "robot":
        raise UnsupportedURDFError(f"not a URDF document: the root element is <{root.tag}>, expected <robot>")
    for ext in root.findall("mujoco"):
        root.remove(ext)
    return ET.tostring(root)


def _parse(text: bytes):
    """The parsed ``urdf_parser_py`` Robot, checked to be one tree of supported joints, and its root link."""
    robot = pk.URDF.from_xml_string(text)
    parents = {}
    for j in robot.joints:
        for end in (j.parent, j.child):
            if end not in robot.link_map:
                raise UnsupportedURDFError(f"joint {j.name!r} names link {end!r}, which is not defined")
        if j.child in parents:
            raise UnsupportedURDFError(
                f"link {j.child!r} is the child of joints {parents[j.child]!r} and {j.name!r}: closed kinematic "
                "loops are not supported (a URDF must be a tree)")
        parents[j.child] = j.name
        if j.mimic is not None:
            raise UnsupportedURDFError(f"joint {j.name!r}: <mimic> joints are not supported")
        if j.type not in ("fixed", *_MJCF_JOINT):
            raise UnsupportedURDFError(
                f"joint {j.name!r} of type {j.type!r}: supported types are fixed, revolute, continuous, prismatic")
        if j.type != "fixed" and j.axis is None:  # the URDF default is x, pytorch-kinematics' is z
            raise UnsupportedURDFError(f"joint {j.name!r} has no <axis>; write it explicitly (pytorch-kinematics "
                                       "reads a missing axis as z, the URDF spec as x)")
        if j.type != "fixed" and not np.linalg.norm(j.axis) > 0:  # _joint normalises it: zero or NaN has no direction
            raise UnsupportedURDFError(f"joint {j.name!r} has a zero-length <axis xyz=\"{_fmt(j.axis)}\">; give the "
                                       "direction it turns about or slides along")
        if j.type in ("revolute", "prismatic") and j.limit is not None and j.limit.lower >= j.limit.upper:
            raise UnsupportedURDFError(
                f"joint {j.name!r}: limit lower {j.limit.lower} >= upper {j.limit.upper} (a missing lower/upper "
                "reads as 0); give a range, or make it continuous or fixed")
    roots = [name for name in robot.link_map if name not in parents]
    if len(roots) != 1:
        raise UnsupportedURDFError(f"a URDF must be one tree with one root link; found roots {roots}")
    return robot, roots[0]


def _translate(robot, root, timestep, armature, ignore_meshes):
    """(MJCF text, link names in MuJoCo body order after the world, movable joint names in qpos order)."""
    mjcf = ET.Element("mujoco", model=robot.name or "urdf")
    ET.SubElement(mjcf, "compiler", angle="radian", inertiafromgeom="false", autolimits="true")
    ET.SubElement(mjcf, "option", timestep=_fmt([timestep]))
    world = ET.SubElement(mjcf, "worldbody")
    actuators = ET.SubElement(mjcf, "actuator")
    links, joints = [], []
    children = {}
    for j in robot.joints:  # document order, as pk's chain builder walks them
        children.setdefault(j.parent, []).append(j)

    def add(link_name, parent_el, joint):
        links.append(link_name)
        body = ET.SubElement(parent_el, "body", name=link_name)
        if joint is not None:
            pos, quat = _origin(joint.origin)
            body.set("pos", _fmt(pos))
            body.set("quat", _fmt(quat))
        link = robot.link_map[link_name]
        _inertial(body, link)
        if joint is not None and joint.type != "fixed":
            _joint(body, actuators, joint, armature)
            joints.append(joint.name)
        for k, col in enumerate(link.collisions):
            _geom(body, f"{link_name}/collision{k}", col, ignore_meshes)
        for child in children.get(link_name, []):
            add(child.child, body, child)

    add(root, world, None)
    return ET.tostring(mjcf, encoding="unicode"), links, joints


def _fmt(values) -> str:
    return " ".join(repr(float(v)) for v in values)


def _origin(origin):
    """URDF ``<origin>`` -> (pos, quat wxyz); ``rpy`` is roll, pitch, yaw about the fixed x, y, z axes."""
    if origin is None:
        return np.zeros(3), np.array([1.0, 0, 0, 0])
    quat = np.array([1.0, 0, 0, 0])
    for axis, angle in zip(np.eye(3), origin.rpy):  # R = Rz(yaw) Ry(pitch) Rx(roll): left-multiply in order
        turn = np.concatenate(([np.cos(angle / 2)], np.sin(angle / 2) * axis))
        mujoco.mju_mulQuat(quat, turn, quat.copy())
    return np.array(origin.xyz, dtype=float), quat


def _inertial(body, link):
    inertial = link.inertial
    if inertial is None or (inertial.mass or 0.0) <= 0:
        return
    pos, quat = _origin(inertial.origin)
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, quat)
    rot = rot.reshape(3, 3)
    tensor = np.array(inertial.inertia.to_matrix() if inertial.inertia else np.zeros((3, 3)), dtype=float)
    tensor = rot @ tensor @ rot.T  # MJCF fullinertia is in the body (link) frame
    full = (tensor[0, 0], tensor[1, 1], tensor[2, 2], tensor[0, 1], tensor[0, 2], tensor[1, 2])
    ET.SubElement(body, "inertial", pos=_fmt(pos), mass=_fmt([inertial.mass]), fullinertia=_fmt(full))


def _joint(body, actuators, joint, armature):
    axis = np.array(joint.axis, dtype=float)
    el = ET.SubElement(body, "joint", name=joint.name, type=_MJCF_JOINT[joint.type], axis=_fmt(axis / np.linalg.norm(axis)),
                       armature=_fmt([armature]))
    if joint.type != "continuous" and joint.limit is not None:
        el.set("range", _fmt([joint.limit.lower, joint.limit.upper]))
    dynamics = joint.dynamics
    if dynamics is not None:
        el.set("damping", _fmt([dynamics.damping or 0.0]))
        if dynamics.friction:
            warnings.warn(f"joint {joint.name!r}: <dynamics friction> is ignored (no joint friction loss in torchsim)",
                          stacklevel=4)
    motor = ET.SubElement(actuators, "motor", name=joint.name, joint=joint.name, gear="1")
    effort = joint.limit.effort if joint.limit is not None else None
    if effort:
        motor.set("ctrlrange", _fmt([-effort, effort]))


def _geom(body, name, collision, ignore_meshes):
    shape = collision.geometry
    pos, quat = _origin(collision.origin)
    if isinstance(shape, shapes.Mesh):
        if ignore_meshes:
            return
        raise UnsupportedURDFError(
            f"{name}: mesh collision geometry ({shape.filename}) is not supported; use box, sphere, cylinder or "
            "capsule primitives, or load with ignore_meshes=True to drop meshes from collision")
    if isinstance(shape, shapes.Box):
        kind, size = "box", np.array(shape.size) / 2
    elif isinstance(shape, shapes.Sphere):
        kind, size = "sphere", [shape.radius]
    elif isinstance(shape, (shapes.Capsule, shapes.Cylinder)):
        kind, size = "capsule", [shape.radius, shape.length / 2]
    else:
        raise UnsupportedURDFError(f"{name}: unsupported collision geometry {type(shape).__name__}")
    ET.SubElement(body, "geom", name=name, type=kind, size=_fmt(size), pos=_fmt(pos), quat=_fmt(quat))


def _check_against_pk(sys: System, text: bytes, links: list, joints: list) -> None:
    """Every link frame of ``sys`` equals pytorch-kinematics' FK at q = 0 and at a configuration turning every
    joint, and ``q`` columns follow pk's joint order."""
    chain = pk.build_chain_from_urdf(text).to(dtype=torch.float64)
    if chain.get_joint_parameter_names() != joints:
        raise UnsupportedURDFError(f"joint order {joints} differs from pytorch-kinematics' "
                                   f"{chain.get_joint_parameter_names()}")
    sys = sys.to(device="cpu", dtype=torch.float64)
    q = torch.stack((torch.zeros(sys.nq, dtype=torch.float64), torch.linspace(-1.0, 1.3, sys.nq, dtype=torch.float64)))
    state = init(sys, q, torch.zeros_like(q))
    pos, quat = mj_body_poses(sys, state.x_pos, state.x_quat)
    fk = chain.forward_kinematics(q)
    for k, link in enumerate(links, start=1):  # MuJoCo body 0 is the world
        ref = fk[link].get_matrix()
        err = max((pos[:, k] - ref[:, :3, 3]).abs().max().item(),
                  (spatial.batch_first.quat_to_mat(quat[:, k]) - ref[:, :3, :3]).abs().max().item())
        if err > _PK_TOLERANCE:
            raise UnsupportedURDFError(
                f"link {link!r}: the translated model differs from pytorch-kinematics' forward kinematics by {err:.1e} "
                "(an unsupported URDF feature, e.g. a link <origin>)")

