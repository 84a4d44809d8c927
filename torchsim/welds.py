"""Weld and connect equality constraints (MuJoCo ``<equality><weld>`` and ``<connect>``) as soft constraint forces on
the bodies, and through them on mocap bodies' poses (``System.mocap_pos``/``mocap_quat``).

Each constraint joins a point and an orientation on each of two sides (``torchsim.io_mjcf.equality``): ``p1``,
``q1`` (side 1's frame times ``relpose``) and ``p2``, ``q2``. Its rows are MuJoCo's residuals:

- translation: ``r = p1 - p2`` (world frame), its rate ``v`` the two points' velocity difference;
- rotation (welds only): ``r = s e_v``, the vector part of the error ``e = q2^-1 q1``, scaled by the
  ``torquescale`` ``s``; its rate ``v = s/2 (e_w u + u x e_v)`` with ``u = R2^T (w1 - w2)`` (MuJoCo's rotation
  Jacobian ``0.5 q2^-1 (w1 - w2) q1``). A connect is a weld with ``s = 0``: no rotation rows.

The rows are MuJoCo's soft constraint, solved on the bare bodies each substep: MuJoCo's force
``f = (A + R)^-1 (aref - a0)`` with ``aref = -B v - K imp r``, ``R = (1 - imp) / imp A0`` (``A0``: MuJoCo's
approximate inverse inertia of the rows at ``qpos0``, the two bodies' ``body_invweight0``, translation or rotation;
``imp``: one impedance per constraint, at the norm of its six residuals), with ``A = J M^-1 J^T`` (6x6) and ``a0``
the rows' acceleration under the substep's other forces and gravity, both of the two bodies as they are, without
the joints (which the method's joint springs and projections handle). Then the rows' acceleration is MuJoCo's
``A (A + R)^-1 (aref - a0) + a0`` for those bodies: a free body is held and driven as in MuJoCo, and at rest a
load leaves MuJoCo's residual ``R f / (K imp)``. The explicit force the other equalities take
(``torchsim.equality``, ``f = imp aref / A0``) leaves out ``a0`` and puts ``A0`` for ``A``: a weld a metre from
a body's COM (``<weld body1="b"/>`` holds it at the world's origin) sees an inverse inertia hundreds of times
``A0`` there, where that force is unstable (its damping alone would remove ``h B A / A0 > 2`` of the rate per
substep; ~15 for a 1 kg box 1.1 m away).
On an articulated body the weld sees the bare link, so it pulls the link and the joints bring the rest along
(``tests/test_mocap_weld.py``: a gripper's path within 3 mm of MuJoCo's).

The translation force acts at ``p1`` on side 1 and opposite at ``p2`` on side 2; the rotation rows' generalized
force ``J^T f`` is the torque ``G^T f`` on side 1 and its opposite on side 2, ``G = s/2 (e_w I - [e_v]x) R2^T``
the rows' Jacobian on ``w1 - w2``.

A mocap body is a frame at its ``mocap_pos``/``mocap_quat`` with zero velocity, as in MuJoCo; a force on it (or on
the world) goes nowhere.

Lanes layout (``torchsim.lanes``): ext-indexed body vectors ``(3, N + 1, B)``, per constraint ``(3, W, B)``.
"""

import torch

from torchsim import lanes, rigid, spatial, tendons
from torchsim.kinematics import Bodies
from torchsim.system import System


def frames(sys: System, bodies: Bodies):
    """The frames the constraints' sides move with: positions, orientations, linear and angular velocities
    ``(3|4, N + 1 + M, B)``, the ext bodies' (COM, body frame) followed by the mocap bodies' (at rest)."""
    batch = bodies.x_pos.shape[-1]
    mocap_pos = lanes.param(sys.mocap_pos, 1, 1).expand(-1, -1, batch)
    mocap_quat = spatial.normalize(lanes.param(sys.mocap_quat, 1, 1)).expand(-1, -1, batch)  # as MuJoCo's kinematics
    rest = torch.zeros_like(mocap_pos)
    return (torch.cat((bodies.x_pos, mocap_pos), -2), torch.cat((bodies.x_quat, mocap_quat), -2),
            torch.cat((bodies.xd_vel, rest), -2), torch.cat((bodies.xd_ang, rest), -2))


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


def wrench(sys: System, bodies: Bodies, inv: rigid.InverseInertia, force: torch.Tensor, torque: torch.Tensor):
    """Ext-indexed world-frame ``(force [N], torque [N m])`` ``(3, N + 1, B)`` of every weld and connect on the
    bodies, the torque about each body's COM (module doc), given the substep's inverse inertias ``inv`` and the
    other forces and torques ``(3, N + 1, B)`` on the bodies (MuJoCo's ``a0``). Only called for a System with welds
    (``sys.welds``)."""
    r, v, arm, err, q2 = residuals(sys, bodies)
    side = sys.weld_body.T.reshape(-1)  # side 1 of every constraint, then side 2; the world for mocap sides
    inv_mass, inv_inertia = (x.unflatten(-2, (2, -1)) for x in rigid.gather(inv, side))  # (2, W, 1|B), (3, 3, 2, W, B)
    moving = (inv.mass > 0).to(force.dtype)
    acc = (lanes.param(sys.gravity, 0, 1)[:, None] * moving + inv.mass * force).index_select(-2, side)
    alpha = spatial.matvec(inv.inertia, torque).index_select(-2, side)
    acc, alpha = acc.unflatten(-2, (2, -1)), alpha.unflatten(-2, (2, -1))  # (3, side, W, B)
    scale = lanes.param(sys.weld_torquescale, 1)
    # rotation rows' rate G (w1 - w2): G = s/2 (e_w I - [e_v]x) R2^T
    g = 0.5 * scale * spatial.mm(err[0] * spatial.eye3(err, 2) - spatial.skew(err[1:]),
                                 spatial.transpose(spatial.quat_to_mat(q2)))
    point_acc = acc + spatial.cross(alpha, arm)
    a0 = torch.cat((point_acc[:, 0] - point_acc[:, 1], spatial.matvec(g, alpha[:, 0] - alpha[:, 1])))
    # the rows' inverse inertia on the bare bodies, A = sum over sides of J M^-1 J^T, in 3x3 blocks
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
    k, b = lanes.param(sys.weld_gains, 2).unbind(-2)
    f = spatial.spd_solve(a, -b * v - k * imp * r - a0)
    moment = spatial.matvec(spatial.transpose(g), f[3:])  # the rotation rows' J^T f
    force_1 = f[:3]
    torque_1 = moment + spatial.cross(arm[:, 0], force_1)
    torque_2 = -moment - spatial.cross(arm[:, 1], force_1)
    zero = bodies.x_pos.new_zeros((6,) + bodies.x_pos.shape[1:])
    total = rigid.scatter_pair(zero, sys.weld_body[:, 0], sys.weld_body[:, 1], torch.cat((force_1, torque_1)),
                               torch.cat((-force_1, torque_2)))
    return total[:3], total[3:]
