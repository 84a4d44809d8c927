"""Fluid forces: MuJoCo's inertia-box model of a body moving through a fluid (``<option density viscosity wind>``).

Each fluid element (a MuJoCo body, see ``torchsim.io_mjcf.fluid``) is the box with its mass and principal inertia.
In the box's frame, with the velocity of its centre relative to the wind ``v`` [m/s] and its angular velocity ``w``
[rad/s], every component feels a viscous (Stokes) and a quadratic (pressure drag) resistance,
``f_k = -(c_k + d_k |u_k|) u_k`` for ``u = (w, v)``, with the loader's coefficients ``c = System.fluid_damping``
(``pi D^3 mu`` on ``w``, ``3 pi D mu`` on ``v``, ``D`` the box's mean side) and ``d = System.fluid_drag``
(``rho b_x (b_y^4 + b_z^4) / 64`` on ``w_x``, ``rho b_y b_z / 2`` on ``v_x``, ...): MuJoCo's
``mj_inertiaBoxFluidModel``, term for term. There is no added mass, lift or Magnus force (that is MuJoCo's ellipsoid model, not supported).

The forces are explicit (from the substep's starting velocities), as MuJoCo's Euler integrator takes them.

Lanes layout (``torchsim.lanes``): ext-indexed body vectors ``(3, N + 1, B)``; per element ``(3, E, B)``.
"""

import torch

from torchsim import lanes, spatial
from torchsim.kinematics import Bodies
from torchsim.system import System


def fluid_wrench(sys: System, bodies: Bodies, rot: torch.Tensor):
    """Ext-indexed world-frame ``(force [N], torque [N m])`` ``(3, N + 1, B)`` of the fluid on every body, the
    torque about the body's COM; ``rot (3, 3, N + 1, B)``: the bodies' rotation matrices. Only called for a System
    with fluid (``sys.fluid``)."""
    idx = sys.fluid_body
    body_rot = rot.index_select(-2, idx)
    arm = spatial.matvec(body_rot, lanes.param(sys.fluid_pos, 1, 1))  # element centre from the body COM, world
    frame = spatial.mm(body_rot, lanes.param(sys.fluid_rot, 1, 2))  # the element box's axes (columns), world
    ang = bodies.xd_ang.index_select(-2, idx)
    vel = bodies.xd_vel.index_select(-2, idx) + spatial.cross(ang, arm) - lanes.param(sys.fluid_wind, 0, 1)[:, None]
    frame_t = spatial.transpose(frame)
    local = torch.cat((spatial.matvec(frame_t, ang), spatial.matvec(frame_t, vel)))  # (6, E, B): (w, v), box frame
    resist = -(lanes.param(sys.fluid_damping, 1, 1) + lanes.param(sys.fluid_drag, 1, 1) * local.abs()) * local
    force = spatial.matvec(frame, resist[3:])
    torque = spatial.matvec(frame, resist[:3]) + spatial.cross(arm, force)  # moved from the element to the COM
    zero = bodies.x_pos.new_zeros((6,) + bodies.x_pos.shape[1:])
    total = zero.index_add(-2, idx, torch.cat((force, torque)))
    return total[:3], total[3:]
