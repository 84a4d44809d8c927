"""MJCF -> :class:`System`, through ``mujoco.MjModel`` (MuJoCo compiles masses, inertias and frames for us).

Supported subset (anything else raises ``UnsupportedMJCFError`` naming the element, or warns where ignoring it
is harmless):
- bodies: any tree; bodies without joints are fused into their parent (mass, COM and inertia combined).
- joints per body: one ``free`` (top-level bodies), one ``ball`` (no limit), or up to 3 ``slide`` followed by up
  to 3 ``hinge`` sharing one anchor (2 hinges: orthogonal axes; 3 hinges: mutually orthogonal axes).
  ``range``, ``damping``, ``armature``, ``stiffness``/``springref`` and ``ref`` on hinges and slides.
- actuators: joint transmission, no activation dynamics, ``gaintype="fixed"``, ``biastype="none"|"affine"``
  (covers ``motor``, ``position`` and ``velocity``), with ``gear``, ``ctrlrange`` and ``forcerange``.
- contact geoms: ``plane`` (static), ``sphere``, ``capsule``, ``box``; pairs from ``contype``/``conaffinity``,
  ``<exclude>``, ``<contact><pair>`` and MuJoCo's parent filter. Geoms of other types that can never touch
  anything (``contype``/``conaffinity`` filtered out) only contribute mass and are accepted with a warning.
"""

import os
import warnings

import mujoco
import numpy as np
import torch

from torchsim import joint_space
from torchsim.collision import SHAPE_RANK
from torchsim.methods import METHODS
from torchsim.system import ContactGroup, System

_SHAPE_NAME = {
    int(mujoco.mjtGeom.mjGEOM_PLANE): "plane",
    int(mujoco.mjtGeom.mjGEOM_SPHERE): "sphere",
    int(mujoco.mjtGeom.mjGEOM_CAPSULE): "capsule",
    int(mujoco.mjtGeom.mjGEOM_BOX): "box",
}
_FREE, _BALL, _SLIDE, _HINGE = (int(mujoco.mjtJoint.mjJNT_FREE), int(mujoco.mjtJoint.mjJNT_BALL),
                                int(mujoco.mjtJoint.mjJNT_SLIDE), int(mujoco.mjtJoint.mjJNT_HINGE))


class UnsupportedMJCFError(ValueError):
    """The model uses an MJCF feature outside torchsim's supported subset (see ``torchsim.io_mjcf``)."""


def load_mjcf(
    source,
    method: str = "spring",
    substeps: int | None = None,
    dtype: torch.dtype = torch.float32,
    device="cpu",
    joint_stiffness: float = 0.2,
    joint_damping: float = 0.5,
    contact_timeconst: float = 0.02,
    xpbd_iterations: int = 1,
    max_speed: float = 1e3,
    max_distance: float = 1e4,
) -> System:
    """Load an MJCF model from a file path or an XML string.

    Args:
        source: path to an ``.xml`` file, or the XML text itself.
        method: ``"xpbd"`` (position-based projection of joints, limits and contacts) or ``"spring"`` (explicit
            stiff springs for joints and limits, velocity impulses for contacts, in the spirit of Brax v1).
        substeps: substeps per ``<option timestep>``; default ``ceil(timestep / h)`` with h = 0.5 ms (ant: 20).
        joint_stiffness: spring method only: fraction of a joint's error its spring removes per substep
            (gain ``stiffness / h^2 K^-1``, ``K`` the joint's inverse-inertia block).
        joint_damping: spring method only: fraction of a joint's error rate its damper removes per substep.
        contact_timeconst: spring method only: MuJoCo's ``solref`` time constant [s] (0.02 s, its default):
            penetration is removed at a separating speed ``depth / (e timeconst)``, the peak speed of MuJoCo's
            critically damped contact pushing out a body that starts that deep (Baumgarte). A per-substep
            fraction instead would launch bodies that start interpenetrating at ``depth / h``. XPBD removes
            penetration in full and zeroes the contacts' normal speed.
        xpbd_iterations: XPBD only: projection passes (contacts, then joint colours) per substep.
        max_speed, max_distance: an env whose body speed [m/s] or distance from the origin [m] exceeds these is
            flagged as diverged.
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; expected one of {tuple(METHODS)}")
    m = _compile(source)
    _check_supported(m)
    substeps = substeps or max(1, int(np.ceil(m.opt.timestep / METHODS[method].default_substep_timestep - 1e-9)))
    fields = _bodies(m)
    fields.update(_joints(m, fields["_ipos"], fields["_off"]))
    fields.update(_actuators(m, fields.pop("_jnt_dof")))
    fields.update(_geoms(m, fields["_ipos"], fields.pop("_off")))
    fields.pop("_ipos")
    gravity = m.opt.gravity * (0.0 if m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_GRAVITY) else 1.0)
    sys = System(
        nq=m.nq, nv=m.nv, nu=m.nu, timestep=float(m.opt.timestep), substeps=int(substeps), method=method,
        gravity=torch.as_tensor(gravity), q0=torch.as_tensor(m.qpos0.copy()),
        joint_stiffness=joint_stiffness, joint_damping=joint_damping, contact_timeconst=contact_timeconst, xpbd_iterations=xpbd_iterations,
        max_speed=max_speed, max_distance=max_distance, **fields,
    )
    return sys.to(device=device, dtype=dtype)


def _compile(source) -> mujoco.MjModel:
    text = str(source)
    if text.lstrip().startswith("<"):
        return mujoco.MjModel.from_xml_string(text)
    if not os.path.isfile(text):
        raise FileNotFoundError(f"MJCF file not found: {text}")
    return mujoco.MjModel.from_xml_path(text)


def _check_supported(m: mujoco.MjModel) -> None:
    unsupported = {
        "tendon": m.ntendon, "equality": m.neq, "flexcomp/flex": m.nflex, "skin": m.nskin,
        "mocap body": m.nmocap, "hfield": m.nhfield,
    }
    for element, count in unsupported.items():
        if count:
            raise UnsupportedMJCFError(
                f"<{element}> is not supported by torchsim ({count} found); see torchsim.io_mjcf for the supported subset"
            )
    if m.njnt and np.any(m.dof_frictionloss != 0):
        raise UnsupportedMJCFError("joint frictionloss is not supported; remove it or set it to 0")
    if m.nsensor:
        warnings.warn(f"{m.nsensor} <sensor> elements are ignored by torchsim", stacklevel=3)


def _name(m, obj, i) -> str:
    return mujoco.mj_id2name(m, obj, i) or f"#{i}"


def _compose(pos_a, quat_a, pos_b, quat_b):
    """Frame b given in frame a -> frame b in a's parent (numpy, float64)."""
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, quat_a)
    quat = np.zeros(4)
    mujoco.mju_mulQuat(quat, quat_a, quat_b)
    return pos_a + rot.reshape(3, 3) @ pos_b, quat


def _bodies(m):
    """Fuse each jointless body into its weld root; combine mass, COM and inertia in the root's frame."""
    off = {0: (np.zeros(3), np.array([1.0, 0, 0, 0]))}  # MuJoCo body -> frame in its weld root (world for 0)
    for b in range(1, m.nbody):
        if m.body_weldid[b] == b:
            off[b] = (np.zeros(3), np.array([1.0, 0, 0, 0]))
        else:
            off[b] = _compose(*off[m.body_parentid[b]], m.body_pos[b], m.body_quat[b])
    roots = [b for b in range(1, m.nbody) if m.body_weldid[b] == b]
    index = {0: len(roots)} | {b: i for i, b in enumerate(roots)}  # ext index; world = N
    mass, ipos, inertia = np.zeros(len(roots)), np.zeros((len(roots), 3)), np.zeros((len(roots), 3, 3))
    for i, r in enumerate(roots):
        members = [b for b in range(1, m.nbody) if m.body_weldid[b] == r]
        coms, tensors = [], []
        for b in members:
            rot = np.zeros(9)
            mujoco.mju_quat2Mat(rot, _compose(*off[b], np.zeros(3), m.body_iquat[b])[1])
            rot = rot.reshape(3, 3)
            coms.append(off[b][0] + _quat_mat(off[b][1]) @ m.body_ipos[b])
            tensors.append(rot @ np.diag(m.body_inertia[b]) @ rot.T)
        masses = m.body_mass[members]
        mass[i] = masses.sum()
        if mass[i] <= 0:
            raise UnsupportedMJCFError(f"body {_name(m, mujoco.mjtObj.mjOBJ_BODY, r)!r} has no mass")
        ipos[i] = (masses[:, None] * np.array(coms)).sum(0) / mass[i]
        for mb, c, t in zip(masses, coms, tensors):
            d = c - ipos[i]
            inertia[i] += t + mb * (d @ d * np.eye(3) - np.outer(d, d))
    parent = [index[m.body_weldid[m.body_parentid[r]]] for r in roots]
    mj_pos = np.array([off[b][0] - (ipos[index[m.body_weldid[b]]] if m.body_weldid[b] else 0) for b in range(m.nbody)])
    return dict(
        body_mass=torch.as_tensor(mass), body_inertia=torch.as_tensor(inertia), body_ipos=torch.as_tensor(ipos),
        body_parent=torch.as_tensor(parent, dtype=torch.long),
        body_names=tuple(_name(m, mujoco.mjtObj.mjOBJ_BODY, r) for r in roots),
        mjbody_body=torch.as_tensor([index[m.body_weldid[b]] for b in range(m.nbody)], dtype=torch.long),
        mjbody_pos=torch.as_tensor(mj_pos), mjbody_quat=torch.as_tensor(np.array([off[b][1] for b in range(m.nbody)])),
        _ipos=ipos, _off=off,
    )


def _quat_mat(q):
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, q)
    return rot.reshape(3, 3)


def _perpendicular(a):
    p = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
    return p / np.linalg.norm(p)


def _joints(m, ipos, off):
    """Group each body's joints into one maximal-coordinate joint, or a free root."""
    index = {0: len(ipos)}
    roots = [b for b in range(1, m.nbody) if m.body_weldid[b] == b]
    index.update({b: i for i, b in enumerate(roots)})
    cols = {k: [] for k in (
        "child", "parent", "anchor_child", "anchor_parent", "quat0", "axes", "mode", "a2_sign", "slide_axes",
        "slide_pinv", "lin_proj")}
    dofs = {k: [] for k in ("flat", "is_hinge", "qpos", "qvel", "limited", "range", "damping", "armature",
                            "stiffness", "springref", "ref", "jnt")}
    ball, free, jnt_dof = ([], [], []), ([], [], []), {}
    for b in roots:
        jids = list(range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b]))
        types = [int(m.jnt_type[j]) for j in jids]
        bname = _name(m, mujoco.mjtObj.mjOBJ_BODY, b)
        for j in jids:
            if types[0] in (_FREE, _BALL) and (m.dof_damping[m.jnt_dofadr[j]] or m.dof_armature[m.jnt_dofadr[j]]
                                               or m.jnt_stiffness[j]):
                raise UnsupportedMJCFError(f"damping/armature/stiffness on the free or ball joint of body {bname!r}")
        if types == [_FREE]:
            if m.body_weldid[m.body_parentid[b]] != 0:
                raise UnsupportedMJCFError(f"free joint of body {bname!r} is not on a top-level body")
            for lst, v in zip(free, (index[b], m.jnt_qposadr[jids[0]], m.jnt_dofadr[jids[0]])):
                lst.append(v)
            continue
        n_slide = sum(t == _SLIDE for t in types)
        n_hinge = sum(t == _HINGE for t in types)
        is_ball = types == [_BALL]
        if not is_ball and (types != [_SLIDE] * n_slide + [_HINGE] * n_hinge or n_slide > 3 or n_hinge > 3):
            raise UnsupportedMJCFError(
                f"body {bname!r} has joints {types} (0 free, 1 ball, 2 slide, 3 hinge); supported per body: one free, "
                "one ball, or up to 3 slides followed by up to 3 hinges")
        hinges = [j for j in jids if m.jnt_type[j] == _HINGE]
        axes = [m.jnt_axis[j] / np.linalg.norm(m.jnt_axis[j]) for j in hinges]
        if hinges and any(np.linalg.norm(m.jnt_pos[j] - m.jnt_pos[hinges[0]]) > 1e-9 for j in hinges):
            raise UnsupportedMJCFError(f"hinges of body {bname!r} must share one anchor (pos)")
        if len(axes) >= 2 and any(abs(axes[i] @ axes[k]) > 1e-6 for i in range(len(axes)) for k in range(i)):
            raise UnsupportedMJCFError(f"the {len(axes)} hinge axes of body {bname!r} must be mutually orthogonal")
        if is_ball and m.jnt_limited[jids[0]]:
            raise UnsupportedMJCFError(f"limited ball joint on body {bname!r} is not supported")
        # the anchor is the hinge/ball pivot; a slide-only joint may use any child point, so take the COM
        anchor_local = m.jnt_pos[hinges[0] if hinges else jids[0]] if (hinges or is_ball) else ipos[index[b]]
        pb = m.body_parentid[b]
        op, oq = off[pb]
        pos0, quat0 = _compose(op, oq, m.body_pos[b], m.body_quat[b])
        parent_ipos = ipos[index[m.body_weldid[pb]]] if m.body_weldid[pb] else np.zeros(3)
        basis = {0: np.eye(3), 1: None, 2: None, 3: None}
        if len(axes) == 1:
            p1 = _perpendicular(axes[0])
            basis[1] = np.stack([axes[0], p1, np.cross(axes[0], p1)])
        elif len(axes) == 2:
            basis[2] = np.stack([axes[0], axes[1], np.cross(axes[0], axes[1])])
        elif len(axes) == 3:
            basis[3] = np.stack(axes)
        slides = [m.jnt_axis[j] / np.linalg.norm(m.jnt_axis[j]) for j in jids if m.jnt_type[j] == _SLIDE]
        s_mat = np.zeros((3, 3))
        s_mat[:, : len(slides)] = np.array(slides).T if slides else 0
        pinv = np.linalg.pinv(s_mat[:, : len(slides)]) if slides else np.zeros((0, 3))
        pinv_pad = np.zeros((3, 3))
        pinv_pad[: len(slides)] = pinv
        ji = len(cols["child"])
        cols["child"].append(index[b])
        cols["parent"].append(index[m.body_weldid[pb]])
        cols["anchor_child"].append(anchor_local - ipos[index[b]])
        cols["anchor_parent"].append(pos0 + _quat_mat(quat0) @ anchor_local - parent_ipos)
        cols["quat0"].append(quat0)
        cols["axes"].append(np.eye(3) if is_ball or not axes else basis[len(axes)])
        cols["mode"].append(np.eye(5)[4 if is_ball else len(axes)])
        cols["a2_sign"].append(axes[0] @ np.cross(axes[1], axes[2]) if len(axes) == 3 else 1.0)  # +-1, handedness
        cols["slide_axes"].append(s_mat.T)
        cols["slide_pinv"].append(pinv_pad)
        cols["lin_proj"].append(np.eye(3) - s_mat @ pinv_pad)
        if is_ball:
            for lst, v in zip(ball, (ji, m.jnt_qposadr[jids[0]], m.jnt_dofadr[jids[0]])):
                lst.append(v)
            continue
        for slot_in_kind, j in enumerate(jids):  # slides fill slots 0.., hinges 3..
            slot = 3 + hinges.index(j) if m.jnt_type[j] == _HINGE else slot_in_kind
            jnt_dof[j] = len(dofs["flat"])
            dofs["flat"].append(ji * 6 + slot)
            dofs["is_hinge"].append(m.jnt_type[j] == _HINGE)
            dofs["qpos"].append(m.jnt_qposadr[j])
            dofs["qvel"].append(m.jnt_dofadr[j])
            dofs["limited"].append(bool(m.jnt_limited[j]))
            dofs["range"].append(m.jnt_range[j])
            dofs["damping"].append(m.dof_damping[m.jnt_dofadr[j]])
            dofs["armature"].append(m.dof_armature[m.jnt_dofadr[j]])
            dofs["stiffness"].append(m.jnt_stiffness[j])
            dofs["springref"].append(m.qpos_spring[m.jnt_qposadr[j]])
            dofs["ref"].append(m.qpos0[m.jnt_qposadr[j]])
            dofs["jnt"].append(ji)

    def t(x, dtype=None, shape=None):
        arr = np.array(x, dtype=dtype)
        return torch.as_tensor(arr.reshape(shape) if arr.size == 0 and shape else arr)

    long = np.int64
    out = {f"jnt_{k}": t(v, long if k in ("child", "parent") else float, (0,) + {
        "anchor_child": (3,), "anchor_parent": (3,), "quat0": (4,), "axes": (3, 3), "mode": (5,), "a2_sign": (),
        "slide_axes": (3, 3), "slide_pinv": (3, 3), "lin_proj": (3, 3)}.get(k, ())) for k, v in cols.items()}
    out["jnt_colors"] = _edge_colors(cols["child"], cols["parent"], len(ipos))
    out["jnt_levels"] = _levels(cols["child"], cols["parent"], len(ipos))
    incidence = joint_space.hinge_incidence(cols["child"], cols["parent"], dofs["jnt"], dofs["is_hinge"], len(ipos))
    out.update(zip(("body_hinge_body", "body_hinge_dof", "body_hinge_sign", "body_hinge_pairs"), incidence))
    slot_dof = np.full(len(cols["child"]) * 6, -1)
    slot_dof[np.array(dofs["flat"], dtype=long)] = np.arange(len(dofs["flat"]))
    out["jnt_slot_dof"] = torch.as_tensor(slot_dof.reshape(-1, 6))
    out["jnt_kinds"] = tuple(bool(k) for k in np.array(cols["mode"]).reshape(-1, 5).any(0))
    out["jnt_has_slides"] = any(np.any(a) for a in cols["slide_axes"])
    for k in ("flat", "qpos", "qvel"):
        out[f"dof_{k}"] = t(dofs[k], long)
    out["dof_is_hinge"] = t(dofs["is_hinge"], bool)
    out["dof_limited"] = t(dofs["limited"], bool)
    out["dof_range"] = t(dofs["range"], float, (0, 2))
    for k in ("damping", "armature", "stiffness", "springref", "ref"):
        out[f"dof_{k}"] = t(dofs[k], float)
    for prefix, lists in (("ball", ball), ("free", free)):
        for k, v in zip(("joint" if prefix == "ball" else "body", "qpos", "qvel"), lists):
            out[f"{prefix}_{k}"] = t(v, long)
    out["_jnt_dof"] = jnt_dof
    return out


def _edge_colors(child, parent, world):
    """Greedy edge colouring: joints of one colour touch disjoint bodies, so they can be solved in parallel."""
    colour_of, used = [], {}
    for c, p in zip(child, parent):
        bodies = [c] + ([p] if p != world else [])
        k = 0
        while any(k in used.get(b, set()) for b in bodies):
            k += 1
        for b in bodies:
            used.setdefault(b, set()).add(k)
        colour_of.append(k)
    return tuple(torch.as_tensor([j for j, k in enumerate(colour_of) if k == c], dtype=torch.long)
                 for c in range(max(colour_of, default=-1) + 1))


def _levels(child, parent, world):
    """Joints grouped by tree depth, so forward kinematics can run level by level."""
    depth = {world: -1}
    for c, p in zip(child, parent):  # MuJoCo orders bodies parent-first
        depth[c] = depth.get(p, 0) + 1
    levels = sorted({depth[c] for c in child})
    return tuple(torch.as_tensor([j for j, c in enumerate(child) if depth[c] == d], dtype=torch.long) for d in levels)


def _actuators(m, jnt_dof):
    for i in range(m.nu):
        name = _name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, i)
        if m.actuator_trntype[i] != int(mujoco.mjtTrn.mjTRN_JOINT) or m.actuator_trnid[i, 0] not in jnt_dof:
            raise UnsupportedMJCFError(f"actuator {name!r}: only joint transmission to a hinge or slide is supported")
        if m.actuator_dyntype[i] != int(mujoco.mjtDyn.mjDYN_NONE):
            raise UnsupportedMJCFError(f"actuator {name!r}: activation dynamics (dyntype) are not supported")
        if m.actuator_gaintype[i] != int(mujoco.mjtGain.mjGAIN_FIXED) or m.actuator_biastype[i] not in (
                int(mujoco.mjtBias.mjBIAS_NONE), int(mujoco.mjtBias.mjBIAS_AFFINE)):
            raise UnsupportedMJCFError(f"actuator {name!r}: only fixed gain and none/affine bias are supported")
    idx = [jnt_dof[m.actuator_trnid[i, 0]] for i in range(m.nu)]
    return dict(
        act_dof=torch.as_tensor(idx, dtype=torch.long),
        act_gear=torch.as_tensor(m.actuator_gear[:, 0].copy()),
        act_gain=torch.as_tensor(m.actuator_gainprm[:, 0].copy()),
        act_bias=torch.as_tensor(m.actuator_biasprm[:, :3].copy()),
        act_ctrl_range=torch.as_tensor(m.actuator_ctrlrange.copy()),
        act_ctrl_limited=torch.as_tensor(m.actuator_ctrllimited.astype(bool)),
        act_force_range=torch.as_tensor(m.actuator_forcerange.copy()),
        act_force_limited=torch.as_tensor(m.actuator_forcelimited.astype(bool)),
    )


def _geoms(m, ipos, off):
    """Geom frames relative to their fused body's COM, and the candidate contact pairs grouped by shape pair."""
    weld = m.body_weldid
    index = {0: len(ipos)} | {b: i for i, b in enumerate(b for b in range(1, m.nbody) if weld[b] == b)}
    gpos, gquat = [], []
    for g in range(m.ngeom):
        b = m.geom_bodyid[g]
        p, q = _compose(*off[b], m.geom_pos[g], m.geom_quat[g])
        gpos.append(p - (ipos[index[weld[b]]] if weld[b] else 0))
        gquat.append(q)
    pairs = {}
    if not m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_CONTACT):
        pairs = _candidate_pairs(m)
    groups = {}
    for (g1, g2), (friction, margin) in pairs.items():
        names = [_SHAPE_NAME.get(int(m.geom_type[g])) for g in (g1, g2)]
        if None in names:
            bad = g1 if names[0] is None else g2
            raise UnsupportedMJCFError(
                f"geom {_name(m, mujoco.mjtObj.mjOBJ_GEOM, bad)!r} of type "
                f"{mujoco.mjtGeom(m.geom_type[bad]).name} can collide; contact geoms must be plane, sphere, "
                "capsule or box (set contype/conaffinity to 0 for visual-only geoms)")
        if names.count("plane") == 1 and weld[m.geom_bodyid[g1 if names[0] == "plane" else g2]] != 0:
            raise UnsupportedMJCFError("planes must belong to the world body")
        (ga, na), (gb, nb) = sorted(((g1, names[0]), (g2, names[1])), key=lambda x: SHAPE_RANK[x[1]])
        groups.setdefault(f"{na}_{nb}", []).append((ga, gb, friction, margin))
    for g in range(m.ngeom):
        if int(m.geom_type[g]) not in _SHAPE_NAME and (m.geom_contype[g] or m.geom_conaffinity[g]):
            warnings.warn(f"geom {_name(m, mujoco.mjtObj.mjOBJ_GEOM, g)!r}: non-primitive geom found no contact "
                          "partner and is used for mass only", stacklevel=3)
    contact_groups = tuple(
        ContactGroup(kind, *(torch.as_tensor([p[i] for p in rows], dtype=torch.long if i < 2 else torch.float64)
                             for i in range(4)))
        for kind, rows in sorted(groups.items()))
    return dict(
        geom_body=torch.as_tensor([index[weld[m.geom_bodyid[g]]] for g in range(m.ngeom)], dtype=torch.long),
        geom_pos=torch.as_tensor(np.array(gpos).reshape(-1, 3)), geom_quat=torch.as_tensor(np.array(gquat).reshape(-1, 4)),
        geom_size=torch.as_tensor(m.geom_size.copy()), contact_groups=contact_groups,
    )


def _candidate_pairs(m):
    """Geom pairs that MuJoCo's broadphase filters would let collide: {(g1, g2): (friction, margin)}."""
    weld, parent = m.body_weldid, m.body_parentid
    filter_parent = not m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_FILTERPARENT)
    excluded = {int(s) for s in m.exclude_signature}
    pairs = {}
    for g1 in range(m.ngeom):
        for g2 in range(g1 + 1, m.ngeom):
            b1, b2 = m.geom_bodyid[g1], m.geom_bodyid[g2]
            w1, w2 = weld[b1], weld[b2]
            if w1 == w2:
                continue
            if not (m.geom_contype[g1] & m.geom_conaffinity[g2] or m.geom_contype[g2] & m.geom_conaffinity[g1]):
                continue
            if filter_parent and w1 and w2 and (weld[parent[w1]] == w2 or weld[parent[w2]] == w1):
                continue
            if ((min(b1, b2) << 16) + max(b1, b2)) in excluded:
                continue
            pairs[(g1, g2)] = (max(m.geom_friction[g1, 0], m.geom_friction[g2, 0]), max(m.geom_margin[g1], m.geom_margin[g2]))
    for p in range(m.npair):
        g1, g2 = sorted((m.pair_geom1[p], m.pair_geom2[p]))
        pairs[(g1, g2)] = (m.pair_friction[p, 0], m.pair_margin[p])
    return pairs
