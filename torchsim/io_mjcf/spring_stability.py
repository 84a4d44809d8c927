"""The spring method's stability number: how far a model's explicit joint springs are from their stability limit.

Each joint's spring and damper are ``kappa / h^2 G`` and ``zeta / h G`` with ``G = K^-1``, ``K`` the joint's
inverse-inertia block (``torchsim.methods.spring``), so a joint alone corrects the fraction ``kappa`` of its error per
substep. A body held by several joints feels the sum of their gains: where a light body carries a much heavier child
(dm_control's jumping ball: a head of 0.11 kg m^2 carrying a camera body of 1 kg m^2 on a hinge and a slide) that sum
exceeds the body's own inertia several times over, and the explicit springs diverge at any substep.

Linearised at ``qpos0``, the springs' substep update is ``v' = v - M^-1 H (kappa x / h + zeta v)``, ``x' = x + h v'``
with ``H = sum_j E_j^T G_j E_j`` (``E_j`` maps the bodies' twists to joint ``j``'s anchor and rotation errors) and
``M`` the bodies' masses and inertias. On an eigenmode of ``M^-1 H`` of eigenvalue ``lam`` this is the symplectic
Euler step of a spring ``kappa lam`` and damper ``zeta lam`` (per substep), which is stable iff
``lam (kappa + 2 zeta) < 4`` (the Jury conditions of its 2x2 update). ``lam`` is the stability number below: 1 for
a body hinged to the world, 1.9 to 3.05 for the envs' models, dm_control's suite and robosuite's arms, 3.53 for
``envs/assets/grasp.xml`` (a 1 kg m^2 palm carrying four 1 kg m^2 fingers 2.25 m out: under the spring method a
passive rollout diverged at the defaults; its env runs XPBD), 4.12 for the jumping ball (``lam (0.2 + 2 * 0.5) = 4.9``:
it diverged within 20 ms at any substep). Joint armature, implicit damping, limits and contacts are not in it, so it
is an estimate: the head-and-camera model of ``tests/test_model_regressions.py`` (3.48, x 1.2 = 4.18) diverges; with
the camera's inertia at 0.3 kg m^2 (3.36, x 1.2 = 4.03) it was stable, at 0.5 (3.42, 4.11) it diverged.

Stable is not accurate: a spring joint yields under the load it carries, by ``h^2 / kappa`` times the load over its
gain, and a robot arm fixed to the world carries its links' weight on joints whose gains are sized on light links
(:func:`gravity_sag`). The loader then raises the default substeps until the sag is within ``SAG_LIMIT``
(:func:`stiff_enough`): the sag goes as ``h^2``.
"""

import math
import warnings
from typing import NamedTuple

import numpy as np
import torch

from torchsim.system import System

# lam (kappa + 2 zeta) above which the loader acts (the limit is 4; the estimate's scatter, above, is ~3%: dm_control's
# boxhead, at 3.72, is stable)
LIMIT = 3.8
# ... and what it lowers it to
TARGET = 3.2
# the stability numbers of the usual models are at most this (the envs' models 1.9 to 3.05, dm_control's suite 1.0 to
# 2.97, robosuite's arms 2.5 to 2.7); above, a light body carries a much heavier child
USUAL = 3.1
# the largest gravity sag [rad] of a joint (:func:`gravity_sag`) the loader's default substeps may leave: robosuite's
# iiwa (5.4e-4 rad at 0.5 ms substeps) tracked MuJoCo at 5.7x MuJoCo's own dt sensitivity, 2.0x at 1.4e-4 rad (8
# substeps), 1.1x at 6e-5 (12); its spot_arm (1.1e-4 rad) at 4.2x, 0.65x at 2.8e-5 (8; over the full 0.5 s 5.8x,
# its elbow stopping on a limit at 0.28 s, and 1.7x at 7e-6 with 16). 7e-6 cannot be the limit: robosuite's jaco
# gripper then gets ~250 substeps and diverges within 2 steps (spring joints on stiff, light links diverge as h
# shrinks, docs/stability.md), where at this limit's 124 it steps. Floating bases sag none.
SAG_LIMIT = 3e-5


class _Linearised(NamedTuple):
    """The springs' linearisation at ``qpos0`` (module docstring), in the bodies a spring acts on (``moving``, System
    indices; ``slot`` maps each to its 6-row block, linear then angular, at its COM)."""
    moving: list
    slot: dict
    a: np.ndarray  # M^-1/2 H M^-1/2 (6 B x 6 B): M^-1 H's eigenvalues, symmetric
    root: np.ndarray  # M^-1/2
    errors: list  # per joint, E_j (6 x 6 B): the bodies' twists -> its anchor [m] and rotation [rad] errors
    mass: np.ndarray  # (B,) [kg] of the moving bodies
    hinge_axes: np.ndarray  # (3, H) the hinge dofs' world axes


def _linearised(sys: System) -> _Linearised | None:
    """``sys``'s springs linearised at ``qpos0``; ``None`` for a model without spring joints."""
    from torchsim import rigid, spatial
    from torchsim.kinematics import dof_values, forward, joint_frames, with_world
    from torchsim.methods.spring import joint_gain

    sys = sys.to(dtype=torch.float64)
    if sys.jnt_child.shape[0] == 0:
        return None
    q0 = sys.q0.reshape(1, -1)
    bodies = with_world(*forward(sys, q0, q0.new_zeros(1, sys.nv)))
    inv = rigid.inverse_inertia(sys, bodies.x_quat, rigid.body_inverse_inertia(sys))
    fr = joint_frames(sys, bodies, rot=inv.rot)
    gain = joint_gain(sys, fr, inv)[..., 0].numpy()  # (3, 3, lin/ang, J)
    child, parent = sys.jnt_child.numpy(), sys.jnt_parent.numpy()
    r_child, r_parent = fr.r_child[..., 0].numpy(), fr.r_parent[..., 0].numpy()
    n = sys.num_bodies
    moving = sorted({int(b) for b in np.concatenate((child, parent)) if b < n})  # bodies a spring acts on
    slot = {b: i for i, b in enumerate(moving)}
    h = np.zeros((6 * len(moving), 6 * len(moving)))
    errors = []
    for j in range(gain.shape[-1]):
        g = np.zeros((6, 6))
        g[:3, :3], g[3:, 3:] = gain[:, :, 0, j], gain[:, :, 1, j]
        e = np.zeros((6, h.shape[0]))
        for b, r, sign in ((int(child[j]), r_child[:, j], 1.0), (int(parent[j]), r_parent[:, j], -1.0)):
            if b < n:  # anchor error: v + w x r = v - [r]x w, rotation error: w
                block = np.eye(6)
                block[:3, 3:] = -spatial.skew(torch.from_numpy(r)).numpy()
                e[:, 6 * slot[b]:6 * slot[b] + 6] += sign * block
        h += e.T @ g @ e
        errors.append(e)
    inv_mass = inv.mass[..., 0].numpy().reshape(-1)
    inv_inertia = inv.inertia[..., 0].numpy()
    root = np.zeros_like(h)  # M^-1/2, so that M^-1/2 H M^-1/2 (symmetric, M^-1 H's eigenvalues) takes eigh
    for b, i in slot.items():
        values, vectors = np.linalg.eigh(inv_inertia[:, :, b])
        root[6 * i:6 * i + 3, 6 * i:6 * i + 3] = np.sqrt(inv_mass[b]) * np.eye(3)
        root[6 * i + 3:6 * i + 6, 6 * i + 3:6 * i + 6] = (vectors * np.sqrt(values.clip(min=0.0))) @ vectors.T
    hinge_axes = dof_values(sys, fr.axes)[..., 0][:, sys.dof_is_hinge].numpy()
    return _Linearised(moving, slot, root @ h @ root, root, errors, 1.0 / inv_mass[moving], hinge_axes)


def stability_number(sys: System) -> tuple[float, int]:
    """``lam``, the largest eigenvalue of ``M^-1 H`` at ``qpos0`` (module docstring), and the body (System index)
    that carries most of its mode's kinetic energy; ``(0.0, -1)`` for a model without spring joints, ``(nan, -1)``
    where an inertia is not finite (the loader then leaves the gains as they are)."""
    lin = _linearised(sys)
    if lin is None:
        return 0.0, -1
    if not np.isfinite(lin.a).all():
        return float("nan"), -1
    values, vectors = np.linalg.eigh(lin.a)
    weight = (vectors[:, -1] ** 2).reshape(-1, 6).sum(1)  # in mass-weighted coordinates: each body's share
    return float(values[-1]), lin.moving[int(np.argmax(weight))]


def gravity_sag(sys: System) -> tuple[float, int]:
    """The spring joints' quasi-static sag under gravity at ``qpos0``: the largest rotation error [rad] of any joint
    and that joint (System index); ``(0.0, -1)`` without spring joints or with an inertia not finite.

    Linearised as in the module docstring, the bodies' displacements ``x`` under their weights ``F`` (``m g`` at each
    COM) obey ``M x'' = F - kappa / h^2 H x``. In the mass-weighted coordinates ``y = M^1/2 x`` the modes of
    ``A = M^-1/2 H M^-1/2`` of eigenvalue 0 are the joints' free motions, which the load accelerates; each
    constrained mode (``lam > 0``) settles at ``y = h^2 / (kappa lam) v^T M^-1/2 F``: the sag, ``h^2 / kappa``
    times the load over the spring's gain. A floating base falls freely and its joints carry no weight (every env
    model in ``envs/assets``: 1e-7 rad or less); a base fixed to the world hangs its links' weight on the joints.

    A planar mechanism whose weight acts across its plane (every hinge axis parallel to gravity) counts as sagging
    none: its joints sag out of the plane, by symmetry a change its motion in the plane does not see at first order
    (gymnasium's and dm_control's reacher and swimmer sag 5e-4 to 3e-3 rad at their default substeps and track
    MuJoCo to 2e-5 rad or better, docs/models.md)."""
    lin = _linearised(sys)
    if lin is None or not np.isfinite(lin.a).all():
        return 0.0, -1
    gravity = sys.gravity.double().numpy()
    directions = np.concatenate((lin.hinge_axes, gravity[:, None] / max(np.linalg.norm(gravity), 1e-300)), 1)
    if not (np.linalg.svd(directions, compute_uv=False)[1:] > 1e-6).any():  # all along one line
        return 0.0, -1
    weight = np.zeros(lin.a.shape[0])
    for i in range(len(lin.moving)):
        weight[6 * i:6 * i + 3] = lin.mass[i] * gravity
    values, vectors = np.linalg.eigh(lin.a)
    constrained = vectors[:, values > 1e-9 * values[-1]]
    values = values[values > 1e-9 * values[-1]]
    sag = lin.root @ constrained @ ((constrained.T @ (lin.root @ weight)) / values)
    sag *= sys.substep_timestep ** 2 / sys.joint_stiffness
    rotation = np.array([np.linalg.norm((e @ sag)[3:]) for e in lin.errors])
    return float(rotation.max()), int(np.argmax(rotation))


def stiff_enough(sys: System, free_substeps: bool) -> System:
    """``sys`` with its substeps raised, where the caller left them to the default (``free_substeps``), until every
    spring joint's gravity sag (:func:`gravity_sag`) is within ``SAG_LIMIT``, with a warning; given substeps are
    kept (the envs choose theirs by measurement), and so are a model's with welds or connects (``sys.welds``): they
    may carry the weight (an arm held by its gripper's weld to a mocap target), and the sag leaves them out."""
    if not free_substeps or sys.welds:
        return sys
    sag, joint = gravity_sag(sys)
    if not sag > SAG_LIMIT:
        return sys
    substeps = math.ceil(sys.substeps * math.sqrt(sag / SAG_LIMIT) - 1e-9)
    body = sys.body_names[int(sys.jnt_child[joint])]
    warnings.warn(f"spring method: substeps {sys.substeps} -> {substeps}: at {sys.substeps} the joints carrying the "
                  f"model's weight would sag {sag:.2g} rad under it (most: the joint of body {body!r}), more than "
                  f"{SAG_LIMIT:g} rad (torchsim.io_mjcf.spring_stability.gravity_sag); give substeps to keep them",
                  stacklevel=3)
    return sys.replace(substeps=substeps)
