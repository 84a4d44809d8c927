"""MuJoCo joints -> torchsim joints: each body's joints grouped into one maximal-coordinate joint, or a free root.

A torchsim joint has six slots, 3 slides then 3 hinges; its dofs fill slots. ``System`` documents the fields.
"""

import mujoco
import numpy as np
import torch

from torchsim import joint_space
from torchsim.io_mjcf.bodies import FusedBodies, compose, quat_mat
from torchsim.io_mjcf.subset import UnsupportedMJCFError, name
from torchsim.io_mjcf.tendons import solref_gains

_FREE, _BALL, _SLIDE, _HINGE = (int(mujoco.mjtJoint.mjJNT_FREE), int(mujoco.mjtJoint.mjJNT_BALL),
                                int(mujoco.mjtJoint.mjJNT_SLIDE), int(mujoco.mjtJoint.mjJNT_HINGE))
#: per-joint fields (``jnt_*``) and the shape of one joint's value; ``child`` and ``parent`` are body indices
JOINT_SHAPES = {"child": (), "parent": (), "anchor_child": (3,), "anchor_parent": (3,), "anchor_offset": (3,),
                "quat0": (4,), "axes": (3, 3), "mode": (5,), "a2_sign": (), "slide_axes": (3, 3), "slide_pinv": (3, 3),
                "lin_proj": (3, 3), "general": (), "anchor_steps": (2, 3)}
#: dtypes of the per-joint fields that are not float
JOINT_DTYPES = {"child": np.int64, "parent": np.int64, "general": bool}
#: per-dof fields (``dof_*``) and their dtypes
DOF_DTYPES = {"flat": np.int64, "is_hinge": bool, "qpos": np.int64, "qvel": np.int64, "limited": bool,
              "range": float, "damping": float, "armature": float, "stiffness": float, "springref": float,
              "ref": float, "frictionloss": float, "margin": float,
              "invweight": float, "solimp": float, "limit_gains": float}
#: the per-dof fields with a value of more than one number, and its shape
DOF_SHAPES = {"range": (2,), "solimp": (5,), "limit_gains": (2,)}


def joint_fields(m: mujoco.MjModel, fused: FusedBodies) -> tuple[dict, dict]:
    """The System's joint, dof, ball and free-body fields; and MuJoCo joint id -> torchsim dof (for actuators)."""
    joints, dofs, jnt_dof = [], [], {}
    ball, free = [], []  # (torchsim joint or body, qpos address, qvel address)
    for b in fused.roots:
        jids = list(range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b]))
        kind = _check_joints(m, b, jids)
        off_com = np.linalg.norm(fused.com[fused.index[b]]) > 1e-9
        if kind == "free" and m.dof_armature[m.jnt_dofadr[jids[0]]] and off_com:
            raise UnsupportedMJCFError(
                f"armature on the free joint of body {name(m, mujoco.mjtObj.mjOBJ_BODY, b)!r}, whose frame's origin "
                "is off its centre of mass, is not supported (its linear armature moves with the origin); damping is")
        if kind == "free":
            free.append((fused.index[b], m.jnt_qposadr[jids[0]], m.jnt_dofadr[jids[0]],
                         *_passive(m, jids[0]), -fused.com[fused.index[b]]))
            continue
        joints.append(_joint(m, b, jids, fused, kind == "ball"))
        if kind == "ball":
            ball.append((len(joints) - 1, m.jnt_qposadr[jids[0]], m.jnt_dofadr[jids[0]], *_passive(m, jids[0]),
                         m.jnt_stiffness[jids[0]], m.qpos_spring[m.jnt_qposadr[jids[0]]:][:4]))
            continue
        hinges = [j for j in jids if m.jnt_type[j] == _HINGE]
        for slot_in_kind, j in enumerate(jids):  # slides fill slots 0.., hinges 3..
            slot = 3 + hinges.index(j) if m.jnt_type[j] == _HINGE else slot_in_kind
            jnt_dof[j] = len(dofs)
            dofs.append(_dof(m, j, len(joints) - 1, slot))
    return _tensors(joints, dofs, ball, free, num_bodies=len(fused.roots)), jnt_dof


def _check_joints(m, b, jids) -> str:
    """``"free"``, ``"ball"`` or ``"slides_hinges"`` for the joints ``jids`` of body ``b``; raises for others."""
    types = [int(m.jnt_type[j]) for j in jids]
    body = name(m, mujoco.mjtObj.mjOBJ_BODY, b)
    for j in jids:
        if types[0] == _FREE and m.jnt_stiffness[j]:
            raise UnsupportedMJCFError(f"stiffness on the free joint of body {body!r} is not supported (damping and "
                                       "armature are)")
        if types[0] in (_FREE, _BALL) and m.dof_frictionloss[m.jnt_dofadr[j]]:
            raise UnsupportedMJCFError(f"frictionloss on the free or ball joint of body {body!r} is not supported "
                                       "(only on hinge and slide joints)")
    if types == [_FREE]:
        if m.body_weldid[m.body_parentid[b]] != 0:
            raise UnsupportedMJCFError(f"free joint of body {body!r} is not on a top-level body")
        return "free"
    if types == [_BALL]:
        if m.jnt_limited[jids[0]]:
            raise UnsupportedMJCFError(f"limited ball joint on body {body!r} is not supported")
        return "ball"
    n_slide, n_hinge = types.count(_SLIDE), types.count(_HINGE)
    if types != [_SLIDE] * n_slide + [_HINGE] * n_hinge or n_slide > 3 or n_hinge > 3:
        raise UnsupportedMJCFError(
            f"body {body!r} has joints {types} (0 free, 1 ball, 2 slide, 3 hinge); supported per body: one free, "
            "one ball, or up to 3 slides followed by up to 3 hinges")
    hinges = [j for j in jids if m.jnt_type[j] == _HINGE]
    axes = _unit_axes(m, hinges)
    # any 2 or 3 hinges compose (torchsim.hinge_anchors), but only the plain form (2 orthogonal hinges, or 3 sharing
    # one anchor on orthogonal axes) at a single anchor may follow slides
    if n_slide and (_is_general(m, hinges) or _anchor_offset(m, hinges).any()):
        raise UnsupportedMJCFError(f"hinges of body {body!r} at different anchors (pos) or on non-orthogonal axes "
                                   "after slide joints are not supported")
    if any(np.linalg.norm(np.cross(axes[i], axes[k])) < 1e-6 for i in range(len(axes)) for k in range(i)):
        raise UnsupportedMJCFError(f"body {body!r} has parallel hinge axes, which are not supported: its orientation "
                                   "gives only the sum of their angles")
    if len(axes) == 3 and abs(axes[0] @ np.cross(axes[1], axes[2])) < 1e-6:
        raise UnsupportedMJCFError(f"the 3 hinge axes of body {body!r} lie in one plane: they cannot turn it about "
                                   "the plane's normal at q = 0 (a gimbal lock)")
    return "slides_hinges"


def _is_general(m, hinges) -> bool:
    """Whether ``hinges`` (of one body) need the general form (``System.jnt_general``): 2 hinges on non-orthogonal
    axes, or 3 hinges on non-orthogonal axes or not all at one anchor."""
    axes = _unit_axes(m, hinges)
    oblique = any(abs(axes[i] @ axes[k]) > 1e-6 for i in range(len(axes)) for k in range(i))
    apart = any(np.linalg.norm(m.jnt_pos[j] - m.jnt_pos[hinges[0]]) > 1e-9 for j in hinges)
    return len(hinges) >= 2 and oblique or len(hinges) == 3 and apart


def _passive(m, j) -> tuple:
    """A free or ball joint's damping and armature, per dof in MuJoCo but one value for all of a joint's dofs in
    MJCF (a joint's attribute): its first dof's."""
    return m.dof_damping[m.jnt_dofadr[j]], m.dof_armature[m.jnt_dofadr[j]]


def _unit_axes(m, jids) -> list:
    return [m.jnt_axis[j] / np.linalg.norm(m.jnt_axis[j]) for j in jids]


def _anchor_offset(m, hinges) -> np.ndarray:
    """The second hinge's anchor minus the first's (body frame) [m] for 2 orthogonal ``hinges``, exact zeros within
    1e-9 (so a model whose hinges share their anchors is flagged as such, ``System.jnt_has_offsets``); else zeros."""
    if len(hinges) != 2 or _is_general(m, hinges):
        return np.zeros(3)
    d = m.jnt_pos[hinges[1]] - m.jnt_pos[hinges[0]]
    return d if np.linalg.norm(d) > 1e-9 else np.zeros(3)


def _joint(m, b, jids, fused: FusedBodies, is_ball: bool) -> dict:
    """One torchsim joint's values (``JOINT_SHAPES``) for body ``b`` and its MuJoCo joints ``jids``."""
    hinge_axes = _unit_axes(m, [j for j in jids if m.jnt_type[j] == _HINGE])
    slides = _unit_axes(m, [j for j in jids if m.jnt_type[j] == _SLIDE])
    com = fused.com[fused.index[b]]
    # the anchor is the hinge/ball pivot; a slide-only joint may use any child point, so take the COM. With hinges
    # at different anchors the child's anchor is the last one, the parent's the first (hinge_anchors)
    hinges = [j for j in jids if m.jnt_type[j] == _HINGE]
    pivot = hinges[:1] or (jids if is_ball else [])
    anchor = m.jnt_pos[pivot[0]] if pivot else com
    offset = _anchor_offset(m, hinges)
    general = _is_general(m, hinges)
    parent = m.body_parentid[b]
    pos0, quat0 = compose(*fused.frame[parent], m.body_pos[b], m.body_quat[b])
    child_anchor = m.jnt_pos[hinges[-1]] if general else anchor + offset
    steps = np.zeros((2, 3))
    if general:
        steps[0] = quat_mat(quat0) @ (m.jnt_pos[hinges[1]] - anchor)
        steps[1] = m.jnt_pos[hinges[2]] - m.jnt_pos[hinges[1]] if len(hinges) == 3 else 0.0
        steps[np.linalg.norm(steps, axis=1) < 1e-9] = 0.0  # a shared anchor is no step (System.jnt_has_offsets)
    slide_cols = np.zeros((3, 3))
    slide_cols[:, : len(slides)] = np.array(slides).T if slides else 0
    slide_pinv = np.zeros((3, 3))
    slide_pinv[: len(slides)] = np.linalg.pinv(slide_cols[:, : len(slides)]) if slides else np.zeros((0, 3))
    return dict(
        child=fused.index[b], parent=fused.body_of(m, parent),
        anchor_child=child_anchor - com, anchor_parent=pos0 + quat_mat(quat0) @ anchor - fused.com_of(m, parent),
        anchor_offset=np.zeros(3) if general else _hinge_basis(hinge_axes) @ offset if hinge_axes else offset,
        quat0=quat0, axes=np.eye(3) if is_ball or not hinge_axes else _hinge_basis(hinge_axes),
        mode=np.eye(5)[4 if is_ball else len(hinge_axes)],
        # +-1: the handedness of 3 hinge axes
        a2_sign=hinge_axes[0] @ np.cross(hinge_axes[1], hinge_axes[2]) if len(hinge_axes) == 3 else 1.0,
        slide_axes=slide_cols.T, slide_pinv=slide_pinv, lin_proj=np.eye(3) - slide_cols @ slide_pinv,
        general=general, anchor_steps=steps,
    )


def _hinge_basis(axes: list) -> np.ndarray:
    """Rows a1, a2, a3 of the joint's zero frame: the hinge axes, completed to a frame."""
    if len(axes) == 1:
        p = np.cross(axes[0], [1.0, 0, 0] if abs(axes[0][0]) < 0.9 else [0, 1.0, 0])
        p = p / np.linalg.norm(p)
        return np.stack([axes[0], p, np.cross(axes[0], p)])
    if len(axes) == 2:  # a3 = a1 x a2, unit where the axes are oblique
        normal = np.cross(axes[0], axes[1])
        oblique = abs(axes[0] @ axes[1]) > 1e-6
        return np.stack([axes[0], axes[1], normal / np.linalg.norm(normal) if oblique else normal])
    return np.stack(axes)


def _dof(m, j, joint: int, slot: int) -> dict:
    """One dof's values (``DOF_DTYPES``, and its joint) for MuJoCo joint ``j`` in ``slot`` of torchsim ``joint``."""
    qpos, qvel = m.jnt_qposadr[j], m.jnt_dofadr[j]
    ref = m.qpos0[qpos]
    return dict(flat=joint * 6 + slot, is_hinge=m.jnt_type[j] == _HINGE, qpos=qpos, qvel=qvel,
                limited=bool(m.jnt_limited[j]), range=m.jnt_range[j], damping=m.dof_damping[qvel],
                armature=m.dof_armature[qvel], stiffness=m.jnt_stiffness[j], springref=m.qpos_spring[qpos],
                ref=ref, frictionloss=m.dof_frictionloss[qvel], jnt=joint,
                # the soft limit (joint_space.limit_rows): MuJoCo's gains at its own timestep, as its step has them
                margin=m.jnt_margin[j], invweight=m.dof_invweight0[qvel], solimp=m.jnt_solimp[j],
                limit_gains=solref_gains(m, m.jnt_solref[j:j + 1], m.jnt_solimp[j:j + 1])[0])


def _tensors(joints: list, dofs: list, ball: list, free: list, num_bodies: int) -> dict:
    """The System's fields from the joints' and dofs' values, with the index structures built from them."""
    def column(rows, key, dtype, shape=()):
        return torch.as_tensor(np.array([r[key] for r in rows], dtype=dtype).reshape(-1, *shape))

    out = {f"jnt_{k}": column(joints, k, JOINT_DTYPES.get(k, float), shape)
           for k, shape in JOINT_SHAPES.items()}
    out |= {f"dof_{k}": column(dofs, k, dtype, DOF_SHAPES.get(k, ())) for k, dtype in DOF_DTYPES.items()}
    out["dof_limits"] = bool(out["dof_limited"].any())
    out["dof_solimp_square"] = bool((out["dof_solimp"][:, 4] == 2).all())
    child, parent = [j["child"] for j in joints], [j["parent"] for j in joints]
    out["jnt_colors"] = _edge_colors(child, parent, num_bodies)
    out["jnt_levels"] = _levels(child, parent, num_bodies)
    incidence = joint_space.hinge_incidence(child, parent, [d["jnt"] for d in dofs], [d["is_hinge"] for d in dofs],
                                            num_bodies)
    out.update(zip(("body_hinge_body", "body_hinge_dof", "body_hinge_sign", "body_hinge_pairs"), incidence))
    slot_dof = np.full(len(joints) * 6, -1)
    slot_dof[out["dof_flat"].numpy()] = np.arange(len(dofs))
    out["jnt_slot_dof"] = torch.as_tensor(slot_dof.reshape(-1, 6))
    out["jnt_kinds"] = tuple(bool(k) for k in out["jnt_mode"].numpy().any(0))
    out["jnt_has_slides"] = bool(out["jnt_slide_axes"].any())
    out["jnt_has_offsets"] = bool(out["jnt_anchor_offset"].any() or out["jnt_anchor_steps"].any())
    out["jnt_has_general"] = bool(out["jnt_general"].any())
    frictional = out["dof_frictionloss"] != 0
    out["dof_friction_hinges"] = torch.nonzero(frictional & out["dof_is_hinge"]).reshape(-1)
    out["dof_friction_slides"] = bool((frictional & ~out["dof_is_hinge"]).any())
    for prefix, first, rows in (("ball", "joint", ball), ("free", "body", free)):
        for i, k in enumerate((first, "qpos", "qvel")):
            out[f"{prefix}_{k}"] = torch.as_tensor(np.array([r[i] for r in rows], dtype=np.int64))
    for prefix, rows, fields in (("ball", ball, (("damping", ()), ("armature", ()), ("stiffness", ()),
                                                 ("spring", (4,)))),
                                 ("free", free, (("damping", ()), ("armature", ()), ("origin", (3,))))):
        for i, (k, shape) in enumerate(fields, start=3):
            out[f"{prefix}_{k}"] = torch.as_tensor(np.array([r[i] for r in rows], dtype=float).reshape(-1, *shape))
    out["root_passive"] = any(bool(out[k].any()) for k in ("ball_damping", "ball_armature", "ball_stiffness",
                                                           "free_damping", "free_armature"))
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
