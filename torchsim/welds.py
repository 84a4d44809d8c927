"""Weld and connect equality constraints (MuJoCo ``<equality><weld>`` and ``<connect>``) as soft constraint impulses on
the bodies, and through them on mocap bodies' poses (``System.mocap_pos``/``mocap_quat``).

Each constraint joins a point and an orientation on each of two sides (``torchsim.io_mjcf.equality``): ``p1``,
``q1`` (side 1's frame times ``relpose``) and ``p2``, ``q2``. Its rows are MuJoCo's residuals:

- translation: ``r = p1 - p2`` (world frame), its rate ``v`` the two points' velocity difference;
- rotation (welds only): ``r = s e_v``, the vector part of the error ``e = q2^-1 q1``, scaled by the
  ``torquescale`` ``s``; its rate ``v = s/2 (e_w u + u x e_v)`` with ``u = R2^T (w1 - w2)`` (MuJoCo's rotation
  Jacobian ``0.5 q2^-1 (w1 - w2) q1``). A connect is a weld with ``s = 0``: no rotation rows.

The rows are MuJoCo's soft constraint, solved each substep as an impulse on the substep's velocities after every
other force (:func:`impulses`): MuJoCo's force ``f = (A + R)^-1 (aref - a0)`` with ``aref = -B v - K imp r``,
``R = (1 - imp) / imp A0`` (``A0``: MuJoCo's approximate inverse inertia of the rows at ``qpos0``, the two bodies'
``body_invweight0``, translation or rotation; ``imp``: one impedance per constraint, at the norm of its six
residuals) and ``A = J M^-1 J^T`` (6x6), times ``h``: ``(A + R) p = v + h aref - v_free``, where ``h a0 = v_free -
v`` is what the substep's other forces, gravity, the joints' springs, armature and damping did to the rows' rate
``v``. A free body is held and driven as in MuJoCo, and at rest a load leaves MuJoCo's residual ``R f / (K imp)``.
``A`` is that of the two bodies as they are, without the joints (which the method's joint springs and projections
handle), each carrying its hinges' armature in the spring method (the inertias its contacts use,
``joint_space.armature_loaded_inertia``): Fetch's gripper (1.7 kg, 0.001-0.003 kg m^2) hangs on a wrist roll
whose rotor has 1 kg m^2 of armature, and sized on the bare link the weld's turn about that axis was undone by the
rotor (the gripper's orientation drifted 18 degrees in 3 steps of random actions, and 62 of 64 envs diverged
within 50). So the weld pulls the link and the joints bring the rest along (``tests/test_mocap_weld.py``: a
gripper's path within 3 mm of MuJoCo's; ``tests/test_fetch_reach.py``: Fetch's grip site within 1.4 mm of
MuJoCo's over six random actions). The explicit force the other equalities take (``torchsim.equality``, ``f = imp
aref / A0``) leaves out ``a0`` and puts ``A0`` for ``A``: a weld a metre from a body's COM (``<weld body1="b"/>``
holds it at the world's origin) sees an inverse inertia hundreds of times ``A0`` there, where that force is
unstable (its damping alone would remove ``h B A / A0 > 2`` of the rate per substep; ~15 for a 1 kg box 1.1 m
away).

The translation impulse acts at ``p1`` on side 1 and opposite at ``p2`` on side 2; the rotation rows' generalized
impulse ``J^T p`` is the angular impulse ``G^T p`` on side 1 and its opposite on side 2, ``G = s/2 (e_w I - [e_v]x) R2^T``
the rows' Jacobian on ``w1 - w2``.

A mocap body is a frame at its ``mocap_pos``/``mocap_quat`` with zero velocity, as in MuJoCo; an impulse on it (or
on the world) goes nowhere.

Lanes layout (``torchsim.lanes``): ext-indexed body vectors ``(3, N + 1, B)``, per constraint ``(3, W, B)``.
"""

import torch

from torchsim import lanes, rigid, spatial, tendons
from torchsim.kinematics import Bodies
from torchsim.system import System


def frames(sys: System, bodies: Bodies):
    """The frames the constraints' sides move with: positions, orientations, linear and angular velocities
    ``(3|4, N + 1 + M, B)``, the ext bodies' (COM, body frame) followed by the mocap bodies' (at rest)."""
    mocap_pos, mocap_quat = mocap_poses(sys, bodies.x_pos.shape[-1])
    return (torch.cat((bodies.x_pos, mocap_pos), -2), torch.cat((bodies.x_quat, mocap_quat), -2),
            *frame_velocities(sys, bodies))


def frame_velocities(sys: System, bodies: Bodies) -> tuple[torch.Tensor, torch.Tensor]:
    """The linear and angular velocities ``(3, N + 1 + M, B)`` of :func:`frames`: the ext bodies', then the mocap
    bodies' (at rest)."""
    vel, ang = bodies.xd_vel, bodies.xd_ang
    rest = vel.new_zeros(3, sys.mocap_pos.shape[-2], vel.shape[-1])
    return torch.cat((vel, rest), -2), torch.cat((ang, rest), -2)


def mocap_poses(sys: System, batch: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The mocap bodies' positions ``(3, M, B)`` and unit orientations ``(4, M, B)`` for a batch of ``batch`` envs."""
    mocap_pos = lanes.param(sys.mocap_pos, 1, 1).expand(-1, -1, batch)
    mocap_quat = spatial.normalize(lanes.param(sys.mocap_quat, 1, 1)).expand(-1, -1, batch)  # as MuJoCo's kinematics
    return mocap_pos, mocap_quat


def residuals(sys: System, bodies: Bodies):
    """MuJoCo's residuals and rates ``(6, W, B)`` (translation rows, then rotation rows; module doc), with what the
    forces need: each side's arm from its frame's origin ``(3, 2, W, B)``, the error quaternion ``e (4, W, B)`` and
    side 2's orientation ``q2 (4, W, B)``."""
    pos, quat, vel, ang = (x.index_select(-2, sys.weld_frame.T.reshape(-1)).unflatten(-2, (2, -1))
                           for x in frames(sys, bodies))  # (3|4, side, W, B)
    arm = spatial.quat_rotate(quat, lanes.param(sys.weld_anchor.transpose(0, 1), 2, 1))
    point_vel = vel + spatial.cross(ang, arm)
    r_lin = (pos[:, 0] + arm[:, 0]) - (pos[:, 1] + arm[:, 1])
    v_lin = point_vel[:, 0] - point_vel[:, 1]
    oriented = spatial.quat_mul(quat, lanes.param(sys.weld_quat.transpose(0, 1), 2, 1))
    q1, q2 = oriented[:, 0], oriented[:, 1]
    err = spatial.quat_mul(spatial.quat_conj(q2), q1)
    scale = lanes.param(sys.weld_torquescale, 1)
    u = spatial.quat_rotate_inv(q2, ang[:, 0] - ang[:, 1])
    r_rot = scale * err[1:]
    v_rot = 0.5 * scale * (err[:1] * u + spatial.cross(u, err[1:]))
    return torch.cat((r_lin, r_rot)), torch.cat((v_lin, v_rot)), arm, err, q2


def _rows(sys: System, bodies: Bodies, inv: rigid.InverseInertia):
    """The rows' residuals and rates ``r, v (6, W, B)``, each side's arm ``(3, 2, W, B)``, the rotation rows'
    Jacobian ``G (3, 3, W, B)`` on ``w1 - w2``, the regularised matrix ``A + R (6, 6, W, B)`` on the bodies of
    ``inv`` and the impedance ``imp (W, B)`` (module doc)."""
    r, v, arm, err, q2 = residuals(sys, bodies)
    side = sys.weld_body.T.reshape(-1)  # side 1 of every constraint, then side 2; the world for mocap sides
    inv_mass, inv_inertia = (x.unflatten(-2, (2, -1)) for x in rigid.gather(inv, side))  # (2, W, 1|B), (3, 3, 2, W, B)
    scale = lanes.param(sys.weld_torquescale, 1)
    # rotation rows' rate G (w1 - w2): G = s/2 (e_w I - [e_v]x) R2^T
    g = 0.5 * scale * spatial.mm(err[0] * spatial.eye3(err, 2) - spatial.skew(err[1:]),
                                 spatial.transpose(spatial.quat_to_mat(q2)))
    # the rows' inverse inertia A = sum over sides of J M^-1 J^T, in 3x3 blocks
    arm_x = spatial.skew(arm)  # (3, 3, side, W, B)
    lever = spatial.mm(arm_x, inv_inertia)
    a_ll = inv_mass.sum(0) * spatial.eye3(arm, 2) - spatial.mm(lever, arm_x).sum(2)
    a_lr = -spatial.mm(lever.sum(2), spatial.transpose(g))
    a_rr = spatial.mm(g, inv_inertia.sum(2), spatial.transpose(g))
    imp = tendons.impedance(sys.weld_solimp, spatial.safe_norm(r))  # at the norm of all six rows, as MuJoCo
    lin, rot = lanes.param(sys.weld_invweight.transpose(0, 1), 2, 1).sum(1)  # A0 of the rows: (W, 1) each
    regulariser = (1 - imp) / imp  # MuJoCo's R / A0
    eye = spatial.eye3(arm, 2)
    a = torch.cat((torch.cat((a_ll + regulariser * lin * eye, a_lr), 1),
                   torch.cat((spatial.transpose(a_lr), a_rr + regulariser * rot * eye), 1)))
    return r, v, arm, g, a, imp


def _rates(sys: System, bodies: Bodies, arm: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """The rows' rates ``(6, W, B)`` under the velocities of ``bodies``, at the poses the arms ``(3, 2, W, B)`` and
    the rotation rows' Jacobian ``G`` of :func:`_rows` were taken at (the rates are linear in the velocities)."""
    vel, ang = (x.index_select(-2, sys.weld_frame.T.reshape(-1)).unflatten(-2, (2, -1))
                for x in frame_velocities(sys, bodies))  # (3, side, W, B)
    point_vel = vel + spatial.cross(ang, arm)
    return torch.cat((point_vel[:, 0] - point_vel[:, 1], spatial.matvec(g, ang[:, 0] - ang[:, 1])))


def impulses(sys: System, start: Bodies, free: Bodies, inv: rigid.InverseInertia, h: float) -> Bodies:
    """``free`` (the substep's velocities after every other force, at the poses of ``start``) after every weld's
    and connect's soft-constraint impulse over the substep ``h``, sized and applied on the inverse inertias ``inv``
    (the spring method's armature-loaded ones, as its contacts). MuJoCo's ``(A + R) f = aref - a0`` times ``h``:
    ``(A + R) p = v + h aref - v_free``, ``v`` the rows' rate at the substep's start, ``v_free`` after the other
    forces (``a0 = (v_free - v) / h``). Only called for a System with welds (``sys.welds``)."""
    r, v, arm, g, a, imp = _rows(sys, start, inv)
    v_free = _rates(sys, free, arm, g)  # the poses are start's: only the velocities changed
    k, b = lanes.param(sys.weld_gains, 2).unbind(-2)
    p = spatial.spd_solve(a, v + h * (-b * v - k * imp * r) - v_free)
    return rigid.apply_pair_velocity(free, inv, sys.weld_body[:, 0], sys.weld_body[:, 1], arm[:, 0], arm[:, 1], p[:3],
                                     spatial.matvec(spatial.transpose(g), p[3:]))
