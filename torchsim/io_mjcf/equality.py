"""MuJoCo ``<equality>`` -> torchsim equality constraints: ``<tendon>`` over fixed tendons and ``<joint>`` over hinge
and slide joints, with ``polycoef``, ``solref`` and ``solimp`` (``torchsim.equality``); ``<weld>`` and ``<connect>``
between bodies or sites, with ``solref``, ``solimp``, ``anchor``, ``relpose`` and ``torquescale`` as MuJoCo compiles
them into ``eq_data`` (``torchsim.welds``).

Only the constraints active at load (``active``, MuJoCo's ``eq_active0``) are kept: torchsim has no runtime switch
(MuJoCo's ``eq_active``), so an inactive one does nothing. Flex constraints are refused naming the constraint,
active or not. ``System`` documents the fields.
"""

import mujoco
import numpy as np
import torch

from torchsim.io_mjcf.bodies import FusedBodies, compose
from torchsim.io_mjcf.subset import UnsupportedMJCFError, name
from torchsim.io_mjcf.tendons import solref_gains, wrap_columns

_WELD, _CONNECT = int(mujoco.mjtEq.mjEQ_WELD), int(mujoco.mjtEq.mjEQ_CONNECT)


def equality_fields(m: mujoco.MjModel, jnt_dof: dict) -> dict:
    """The System's ``eq_*`` fields; ``jnt_dof``: MuJoCo joint id -> torchsim dof."""
    for e in range(m.neq):
        _check(m, e, jnt_dof)
    kept = [e for e in _active(m) if m.eq_type[e] not in (_WELD, _CONNECT)]
    n = len(kept)
    wraps, ref, invweight = [], np.zeros((n, 2)), np.zeros(n)  # wraps: (side row, dof, coef)
    for i, e in enumerate(kept):
        for side, obj in enumerate((m.eq_obj1id[e], m.eq_obj2id[e])):
            if obj < 0:
                continue
            if m.eq_type[e] == int(mujoco.mjtEq.mjEQ_TENDON):
                adr = range(m.tendon_adr[obj], m.tendon_adr[obj] + m.tendon_num[obj])
                wraps += [(side * n + i, jnt_dof[m.wrap_objid[w]], m.wrap_prm[w]) for w in adr]
                ref[i, side], invweight[i] = m.tendon_length0[obj], invweight[i] + m.tendon_invweight0[obj]
            else:
                wraps.append((side * n + i, jnt_dof[obj], 1.0))
                ref[i, side] = m.qpos0[m.jnt_qposadr[obj]]
                invweight[i] += m.dof_invweight0[m.jnt_dofadr[obj]]
    polycoef = m.eq_data[kept, :5].reshape(n, 5).copy()
    polycoef[m.eq_obj2id[kept] < 0, 1:] = 0.0  # one side: r = x1 - a0
    solref, solimp = m.eq_solref[kept].reshape(n, 2), m.eq_solimp[kept].reshape(n, 5)
    return dict(
        zip(("eq_wrap_side", "eq_wrap_dof", "eq_wrap_coef"), wrap_columns(wraps)),
        eq_ref=torch.as_tensor(ref), eq_polycoef=torch.as_tensor(polycoef),
        eq_solimp=torch.as_tensor(solimp.copy()), eq_gains=torch.as_tensor(solref_gains(m, solref, solimp)),
        eq_invweight=torch.as_tensor(invweight), eq_constraints=n > 0,
    )


def weld_fields(m: mujoco.MjModel, fused: FusedBodies) -> dict:
    """The System's ``weld_*`` fields: the active ``<weld>`` and ``<connect>`` constraints (``torchsim.welds``).

    Each side's point and orientation are put in the frame it moves with: its fused body's (from the COM), a mocap
    body's, or the world's. MuJoCo's ``eq_data`` holds, for a connect, the anchors on body 1 (``[0:3]``) and body 2
    (``[3:6]``); for a weld, the anchor on body 2 (``[0:3]``), the matching point on body 1 (``[3:6]``), ``relpose``'s
    quaternion (``[6:10]``) and ``torquescale`` (``[10]``); with sites, the sites' frames replace them (``relpose``
    unused)."""
    kept = [e for e in _active(m) if m.eq_type[e] in (_WELD, _CONNECT) and not _idle(m, e)]
    n = len(kept)
    frame, body, anchor, quat = np.zeros((n, 2), int), np.zeros((n, 2), int), np.zeros((n, 2, 3)), np.zeros((n, 2, 4))
    torquescale, invweight = np.zeros(n), np.zeros((n, 2, 2))
    for i, e in enumerate(kept):
        data, weld = m.eq_data[e], m.eq_type[e] == _WELD
        sites = m.eq_objtype[e] == int(mujoco.mjtObj.mjOBJ_SITE)
        for side, obj in enumerate((m.eq_obj1id[e], m.eq_obj2id[e])):
            mj_body = m.site_bodyid[obj] if sites else obj
            if sites:
                local = (m.site_pos[obj], m.site_quat[obj])
            else:  # a weld's first anchor is body 1's point, [3:6]
                local = (data[3 * (1 - side):3 * (2 - side)] if weld else data[3 * side:3 * side + 3],
                         data[6:10] if weld and side == 0 else np.array([1.0, 0, 0, 0]))
            frame[i, side], *pose = fused.moving_frame(m, mj_body)  # a mocap body's own frame for its side
            pos, q = compose(*pose, *local)
            body[i, side] = fused.body_of(m, mj_body)
            anchor[i, side] = pos
            quat[i, side] = q / np.linalg.norm(q)
            invweight[i, side] = m.body_invweight0[mj_body]
        torquescale[i] = data[10] if weld else 0.0
    solref, solimp = m.eq_solref[kept].reshape(n, 2), m.eq_solimp[kept].reshape(n, 5).copy()
    return dict(
        weld_frame=torch.as_tensor(frame), weld_body=torch.as_tensor(body), weld_anchor=torch.as_tensor(anchor),
        weld_quat=torch.as_tensor(quat), weld_torquescale=torch.as_tensor(torquescale),
        weld_solimp=torch.as_tensor(solimp), weld_gains=torch.as_tensor(solref_gains(m, solref, solimp)),
        weld_invweight=torch.as_tensor(invweight), welds=n > 0,
    )


def _idle(m: mujoco.MjModel, e: int) -> bool:
    """Whether weld or connect ``e`` moves nothing: both sides on one rigid body (one weld root), or each on the
    world or a mocap body. MuJoCo drops such a constraint (its Jacobian is empty)."""
    bodies = [m.eq_obj1id[e], m.eq_obj2id[e]]
    if m.eq_objtype[e] == int(mujoco.mjtObj.mjOBJ_SITE):
        bodies = [m.site_bodyid[b] for b in bodies]
    roots = [m.body_weldid[b] for b in bodies]
    return roots[0] == roots[1] or all(r == 0 or m.body_mocapid[r] >= 0 for r in roots)


def _active(m: mujoco.MjModel) -> list:
    """The equality constraints active at load (none where the model disables equality constraints)."""
    disabled = m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_EQUALITY | mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
    return [] if disabled else [e for e in range(m.neq) if m.eq_active0[e]]


def _check(m: mujoco.MjModel, e: int, jnt_dof: dict) -> None:
    kind = mujoco.mjtEq(m.eq_type[e]).name.removeprefix("mjEQ_").lower()
    constraint = name(m, mujoco.mjtObj.mjOBJ_EQUALITY, e)
    if kind not in ("tendon", "joint", "weld", "connect"):
        raise UnsupportedMJCFError(f"equality constraint {constraint!r}: <{kind}> equality constraints are not "
                                   "supported (only <tendon> over fixed tendons, <joint> over hinges and slides, "
                                   "<weld> and <connect>)")
    for obj in (m.eq_obj1id[e], m.eq_obj2id[e]):
        if kind == "joint" and obj >= 0 and obj not in jnt_dof:
            joint = name(m, mujoco.mjtObj.mjOBJ_JOINT, obj)
            raise UnsupportedMJCFError(f"equality constraint {constraint!r}: joint {joint!r} is not a hinge or slide "
                                       "(a <joint> equality constraint may only couple hinges and slides)")
