"""Semi-implicit Euler for rigid bodies: forces -> velocities (implicit gyroscopic term), velocities -> poses.

Lanes layout (``torchsim.lanes``): ext-indexed vectors ``(3, N + 1, B)``, quaternions ``(4, N + 1, B)``.
"""

import torch

from torchsim import lanes, spatial, rigid
from torchsim.kinematics import Bodies
from torchsim.system import System


def velocity_update(sys: System, bodies: Bodies, inv: rigid.InverseInertia, force: torch.Tensor,
                    torque: torch.Tensor, h: float) -> Bodies:
    """Advance velocities by ``h`` under gravity and ext-indexed ``force``/``torque (3, N + 1, B)`` (world frame).

    The gyroscopic term ``w x I w`` is taken implicitly with one Newton step in the body frame (Catto's scheme),
    which keeps a freely spinning body's energy and momentum bounded at large ``h``. Frames change through the
    rotation matrices ``inv.rot`` (a product with a matrix costs half a quaternion rotation).
    """
    n = sys.num_bodies
    moving = (inv.mass > 0).to(force.dtype)
    gravity = lanes.param(sys.gravity, 0, 1)[:, None]  # (3, 1, 1 | B): one value for every body
    xd_vel = bodies.xd_vel + h * (gravity * moving + inv.mass * force)
    rot = inv.rot[..., :n, :]
    rot_t = spatial.transpose(rot)
    w_body = spatial.matvec(rot_t, bodies.xd_ang[..., :n, :])
    torque_body = spatial.matvec(rot_t, torque[..., :n, :])
    inertia = lanes.param(sys.body_inertia, 1, 2)
    i_w = spatial.matvec(inertia, w_body)
    residual = h * spatial.cross(w_body, i_w) - h * torque_body
    jac = inertia + h * (spatial.skew_mm(w_body, inertia) - spatial.skew(i_w))
    w_body = w_body - spatial.matvec(spatial.inv3(jac), residual)
    xd_ang = torch.cat((spatial.matvec(rot, w_body), bodies.xd_ang[..., n:, :]), -2)
    return bodies._replace(xd_vel=xd_vel, xd_ang=xd_ang)


def integrate_positions(bodies: Bodies, h: float) -> Bodies:
    """``x += h v`` and the exact exponential-map rotation of each orientation by ``h w`` (all ``(*C, N + 1, B)``)."""
    return bodies._replace(x_pos=bodies.x_pos + h * bodies.xd_vel,
                           x_quat=spatial.quat_integrate(bodies.x_quat, bodies.xd_ang, h))
