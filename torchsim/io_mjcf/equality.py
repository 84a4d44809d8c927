"""MuJoCo ``<equality>`` -> torchsim equality constraints (``torchsim.equality``): ``<tendon>`` over fixed tendons
and ``<joint>`` over hinge and slide joints, with ``polycoef``, ``solref`` and ``solimp``.

Only the constraints active at load (``active``, MuJoCo's ``eq_active0``) are kept: torchsim has no runtime switch
(MuJoCo's ``eq_active``), so an inactive one does nothing. ``connect``, ``weld`` and flex constraints are refused
naming the constraint and its type, active or not. ``System`` documents the fields.
"""

import mujoco
import numpy as np
import torch

from torchsim.io_mjcf.subset import UnsupportedMJCFError, name
from torchsim.io_mjcf.tendons import solref_gains, wrap_columns


def equality_fields(m: mujoco.MjModel, jnt_dof: dict) -> dict:
    """The System's ``eq_*`` fields; ``jnt_dof``: MuJoCo joint id -> torchsim dof."""
    for e in range(m.neq):
        _check(m, e, jnt_dof)
    disabled = m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_EQUALITY | mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
    kept = [] if disabled else [e for e in range(m.neq) if m.eq_active0[e]]
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


def _check(m: mujoco.MjModel, e: int, jnt_dof: dict) -> None:
    kind = mujoco.mjtEq(m.eq_type[e]).name.removeprefix("mjEQ_").lower()
    constraint = name(m, mujoco.mjtObj.mjOBJ_EQUALITY, e)
    if kind not in ("tendon", "joint"):
        raise UnsupportedMJCFError(f"equality constraint {constraint!r}: <{kind}> equality constraints are not "
                                   "supported (only <tendon> over fixed tendons and <joint> over hinges and slides)")
    for obj in (m.eq_obj1id[e], m.eq_obj2id[e]):
        if kind == "joint" and obj >= 0 and obj not in jnt_dof:
            joint = name(m, mujoco.mjtObj.mjOBJ_JOINT, obj)
            raise UnsupportedMJCFError(f"equality constraint {constraint!r}: joint {joint!r} is not a hinge or slide "
                                       "(a <joint> equality constraint may only couple hinges and slides)")
