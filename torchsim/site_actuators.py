"""Site transmission (MuJoCo ``<general site=...>``, ``<motor site=...>``, optionally with ``refsite``): an
actuator's 6D ``gear`` as a wrench at a site, with MuJoCo's length, velocity and moment arms.

Without a refsite the wrench direction is the gear in the site's frame: a force ``R_site gear[:3]`` at the site and
a torque ``R_site gear[3:]`` on its body; the length is 0 and the velocity the gear's component of the site's
(linear, angular) velocity. With a refsite (MuJoCo's Cartesian mode) the gear is in the refsite's frame, the length
is the gear's component of the site's pose relative to the refsite (the position difference and the rotation
vector of the relative rotation, both in the refsite's frame), and the wrench acts on the site's body at the site
and, equal and opposite, on the refsite's body at that same point: MuJoCo's moment is the difference of the two
bodies' Jacobians at the site's position (its velocity, checked against MuJoCo's in ``tests/test_site_actuators.py``,
is the refsite's body's velocity at the site, not the refsite's), and the wrench on the bodies exerts its
generalized forces through the joints. The velocity is that moment times ``qvel``, as in MuJoCo (not the length's
time derivative: the refsite's frame turns).

Tensors are in the lanes layout: ext-indexed bodies ``(3|4, N + 1, B)``, per site actuator ``(S, B)``, vectors
``(3, S, B)``.
"""

from typing import NamedTuple

import torch

from torchsim import lanes, rigid, spatial
from torchsim.kinematics import Bodies
from torchsim.system import System


class SiteCoordinates(NamedTuple):
    """The site actuators' transmission at the bodies' poses and velocities.

    Attributes:
        length, velocity: (S, B) MuJoCo's ``actuator_length`` [m | rad] and ``actuator_velocity``.
        force_dir, torque_dir: (3, S, B) the wrench a unit actuator force exerts, world frame.
        arm: (3, 2, S, B) the site from the COMs of its body and of the refsite's body, world frame [m].
    """

    length: torch.Tensor
    velocity: torch.Tensor
    force_dir: torch.Tensor
    torque_dir: torch.Tensor
    arm: torch.Tensor


def coordinates(sys: System, bodies: Bodies) -> SiteCoordinates:
    """:class:`SiteCoordinates` at ext ``bodies``."""
    body = sys.site_act_body.flatten()  # sites, then refsites

    def at_sites(x):  # (C, N + 1, B) -> (C, 2, S, B)
        return x.index_select(-2, body).unflatten(-2, sys.site_act_body.shape)

    quat = at_sites(bodies.x_quat)
    site_quat = spatial.quat_mul(quat, lanes.param(sys.site_act_quat, 2, 1))
    com = at_sites(bodies.x_pos)
    site_pos = com + spatial.quat_rotate(quat, lanes.param(sys.site_act_pos, 2, 1))
    arm = site_pos[:, :1] - com  # the site on both bodies
    spin = at_sites(bodies.xd_ang)
    speed = at_sites(bodies.xd_vel) + spatial.cross(spin, arm)  # of the points of both bodies at the site
    has_ref = lanes.param(sys.site_act_has_ref, 1)
    frame = torch.where(has_ref, site_quat[:, 1], site_quat[:, 0])  # the gear's frame
    gear = lanes.param(sys.site_act_gear, 1, 1)
    force_dir, torque_dir = spatial.quat_rotate(frame, gear[:3]), spatial.quat_rotate(frame, gear[3:])
    # a site without a refsite: the refsite row is the world's origin, at rest
    velocity = spatial.dot(force_dir, speed[:, 0] - speed[:, 1]) + spatial.dot(torque_dir, spin[:, 0] - spin[:, 1])
    offset = spatial.quat_rotate_inv(site_quat[:, 1], site_pos[:, 0] - site_pos[:, 1])
    turn = spatial.quat_to_rot_vec(spatial.quat_mul(spatial.quat_conj(site_quat[:, 1]), site_quat[:, 0]))
    length = torch.where(has_ref, spatial.dot(gear[:3], offset) + spatial.dot(gear[3:], turn), 0.0)
    return SiteCoordinates(length, velocity, force_dir, torque_dir, arm)


def wrench(sys: System, bodies: Bodies, site: SiteCoordinates, force: torch.Tensor):
    """Ext-indexed ``(force, torque)`` ``(3, N + 1, B)`` of the site actuators' forces ``force (S, B)``: the wrench
    at each site on its body, and its opposite at the same point on the refsite's body (the world, which does not
    move, where there is none)."""
    lin, ang = force * site.force_dir, force * site.torque_dir
    site_body, ref_body = sys.site_act_body
    return (rigid.scatter_pair(torch.zeros_like(bodies.x_pos), site_body, ref_body, lin, -lin),
            rigid.scatter_pair(torch.zeros_like(bodies.x_pos), site_body, ref_body,
                               ang + spatial.cross(site.arm[:, 0], lin), -ang - spatial.cross(site.arm[:, 1], lin)))
