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
"""

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


def stability_number(sys: System) -> tuple[float, int]:
    """``lam``, the largest eigenvalue of ``M^-1 H`` at ``qpos0`` (module docstring), and the body (System index)
    that carries most of its mode's kinetic energy; ``(0.0, -1)`` for a model without spring joints, ``(nan, -1)``
    where an inertia is not finite (the loader then leaves the gains as they are)."""
    from torchsim import rigid, spatial
    from torchsim.kinematics import forward, joint_frames, with_world
    from torchsim.methods.spring import joint_gain

    sys = sys.to(dtype=torch.float64)
    if sys.jnt_child.shape[0] == 0:
        return 0.0, -1
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
    inv_mass = inv.mass[..., 0].numpy().reshape(-1)
    inv_inertia = inv.inertia[..., 0].numpy()
    root = np.zeros_like(h)  # M^-1/2, so that M^-1/2 H M^-1/2 (symmetric, M^-1 H's eigenvalues) takes eigh
    for b, i in slot.items():
        values, vectors = np.linalg.eigh(inv_inertia[:, :, b])
        root[6 * i:6 * i + 3, 6 * i:6 * i + 3] = np.sqrt(inv_mass[b]) * np.eye(3)
        root[6 * i + 3:6 * i + 6, 6 * i + 3:6 * i + 6] = (vectors * np.sqrt(values.clip(min=0.0))) @ vectors.T
    a = root @ h @ root
    if not np.isfinite(a).all():
        return float("nan"), -1
    values, vectors = np.linalg.eigh(a)
    weight = (vectors[:, -1] ** 2).reshape(-1, 6).sum(1)  # in mass-weighted coordinates: each body's share
    return float(values[-1]), moving[int(np.argmax(weight))]
