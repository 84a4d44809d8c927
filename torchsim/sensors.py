"""MuJoCo's sensors read from a State: ``(system, state) -> (B, nsensordata)`` in MuJoCo's ``sensordata`` layout.

    data = torchsim.sensordata(sys, state)                  # (B, nsensordata), MuJoCo's layout
    gyro = torchsim.sensor(sys, state, "imu_gyro")          # (B, 3), one sensor by name
    obs = torchsim.sensors_by_name(sys, state, ctrl)        # {name: (B, dim)} of every computed sensor

Batched and differentiable torch ops on the public (batch-first) State, never part of the step. The values are
MuJoCo's definitions evaluated at the State: frames (sites, geoms, bodies, cameras) from the body poses, where
``State.x_pos`` is each body's centre of mass; velocities of points from the body's COM velocity and angular
velocity; joint, tendon and actuator quantities from ``q``/``qd``; energies from the bodies' masses, inertias and
poses, the springs and the rotors (armature). Actuator forces (``actuatorfrc``,
``jointactuatorfrc``, ``tendonactuatorfrc``) follow the actuator model at the given controls, as MuJoCo's
``actuator_force``; the State does not keep the last controls, so these take ``ctrl``. After ``mj_step`` MuJoCo's
``sensordata`` holds the values at the state the step started from: compare with these at that State.

Accelerations and the forces that follow from them are not in the State. ``accelerometer``, ``framelinacc``,
``frameangacc``, ``force`` and ``torque`` read the mean acceleration over the next step, ``(v' - v) / timestep``
between the State and the one ``torchsim.step`` reaches from it under ``ctrl`` (one extra step per read; pass
``next_state`` where the caller has stepped already), where MuJoCo reads the instantaneous acceleration at the
step's start: the two agree at rest and under constant acceleration, and otherwise differ by about half the change
of the acceleration over a step (site frames and moment arms are taken midway through the step, as the means are).
As MuJoCo's, the linear ones read the acceleration less gravity (an accelerometer at rest reads ``+g`` upwards; one
fixed to the world reads 0). ``force`` and ``torque`` are MuJoCo's ``cfrc_int`` at the site: the wrench the site's
body's parent puts on the body's subtree, by Newton-Euler over the subtree's bodies (their mean rates of change of
momentum and angular momentum over the step, less gravity) less the contact forces on it, in the site's frame. The
contact forces these and ``touch`` read are the spring method's (``torchsim.contact_forces``; another method is
refused where the model has contacts), averaged over the step's substeps: they step again for them even when given
``next_state``.

The step's accelerations are torchsim's dynamics, not a closed form: right after ``init`` the spring method's joints
are unloaded and their first steps take up the load (a pendulum released at rest reads up to 11 m/s^2 off in its
first step, 0.02 ten steps on), and a body still settling into a contact reads its settling.

Which types are computed, and why the others are not: ``torchsim.io_mjcf.sensors``. ``System`` documents the fields.
"""

import torch

from torchsim import activation, actuators, lanes, spatial, tendon_paths, tendons
from torchsim.contact_forces import ContactForces, SubstepContacts, mean_contact_forces, step_contacts
from torchsim.io_mjcf.sensors import ACC_KINDS, FRAME_KINDS, SUBTREE_KINDS, WRENCH_KINDS
from torchsim.io_mjcf.subset import UnsupportedMJCFError
from torchsim.kinematics import _addresses, with_world
from torchsim.pipeline import check, step, to_lanes_state
from torchsim.render import raycast
from torchsim.state import State
from torchsim.system import SensorGroup, System

#: The sensor types that read forces which depend on the controls: actuator forces, contact forces.
FORCE_KINDS = ("actuatorfrc", "jointactuatorfrc", "tendonactuatorfrc", "touch")
#: The sensor types read over the next step (see the module), which depends on the controls.
STEP_KINDS = ACC_KINDS + WRENCH_KINDS
AXIS_COLUMN = {"framexaxis": 0, "frameyaxis": 1, "framezaxis": 2}


def sensordata(sys: System, state: State, ctrl: torch.Tensor | None = None,
               next_state: State | None = None) -> torch.Tensor:
    """Every sensor ``(B, nsensordata)`` in MuJoCo's ``sensordata`` layout; the slots of sensors torchsim does not
    compute (``sys.sensor_skipped``) read NaN. ``ctrl (B, nu)``: needed where the model has actuator-force, touch,
    acceleration, force or torque sensors. ``next_state``: ``torchsim.step(sys, state, ctrl)`` if the caller has
    it, which the acceleration, force and torque sensors then read instead of stepping again."""
    return lanes.from_lanes(_read(sys, state, ctrl, sys.sensor_groups, next_state))


def sensor(sys: System, state: State, name: str, ctrl: torch.Tensor | None = None,
           next_state: State | None = None) -> torch.Tensor:
    """Sensor ``name``'s value ``(B, dim)``; ``ctrl (B, nu)`` and ``next_state`` as :func:`sensordata`. Raises for a
    name the model lacks and for a sensor torchsim does not compute."""
    i = _index(sys, name)
    groups = tuple(g for g in sys.sensor_groups if g.kind == sys.sensor_kinds[i])
    adr = sys.sensor_adr[i]
    return lanes.from_lanes(_read(sys, state, ctrl, groups, next_state)[adr:adr + sys.sensor_dims[i]])


def sensors_by_name(sys: System, state: State, ctrl: torch.Tensor | None = None,
                    next_state: State | None = None) -> dict:
    """``{name: (B, dim)}`` for every sensor torchsim computes, in MuJoCo's order."""
    data = sensordata(sys, state, ctrl, next_state)
    return {n: data[:, a:a + d] for n, a, d, skipped in
            zip(sys.sensor_names, sys.sensor_adr, sys.sensor_dims, sys.sensor_skipped) if not skipped}


def _index(sys: System, name: str) -> int:
    if name not in sys.sensor_names:
        raise KeyError(f"the model has no sensor {name!r}; its sensors: {', '.join(sys.sensor_names) or 'none'}")
    i = sys.sensor_names.index(name)
    if sys.sensor_skipped[i]:
        raise UnsupportedMJCFError(f"sensor {name!r} ({sys.sensor_kinds[i]}) is not computed by torchsim: "
                                   f"{sys.sensor_skipped[i]}")
    return i


class _Frames:
    """The sensor frames in the world, lanes layout ``(3|4, F, B)``: origin, orientation, origin's velocity and
    angular velocity."""

    def __init__(self, sys: System, state: State):
        bodies = with_world(*to_lanes_state(state)[:4])
        pos, quat, vel, ang = (t.index_select(-2, sys.sensor_frame_body) for t in bodies)
        offset = spatial.quat_rotate(quat, lanes.param(sys.sensor_frame_pos, 1, 1))  # from the body COM
        self.pos = pos + offset
        self.quat = spatial.quat_mul(quat, lanes.param(sys.sensor_frame_quat, 1, 1))
        self.vel = vel + spatial.cross(ang, offset)
        self.ang = ang

    def at(self, index: torch.Tensor):
        return tuple(t.index_select(-2, index) for t in (self.pos, self.quat, self.vel, self.ang))


def _frame_values(sys: System, frames: _Frames, group: SensorGroup) -> torch.Tensor:
    """A frame sensor group's values ``(dim, S, B)``: the object frame relative to the reference frame, as
    MuJoCo's (the world where a sensor names none); gyros, velocimeters and magnetometers in their site's frame."""
    pos, quat, vel, ang = frames.at(group.obj)
    ref_pos, ref_quat, ref_vel, ref_ang = frames.at(group.ref)
    kind = group.kind
    if kind == "framepos":
        return spatial.quat_rotate_inv(ref_quat, pos - ref_pos)
    if kind == "framequat":
        return spatial.quat_mul(spatial.quat_conj(ref_quat), quat)
    if kind in AXIS_COLUMN:  # a column of the object's rotation matrix
        return spatial.quat_rotate_inv(ref_quat, spatial.quat_to_mat(quat)[:, AXIS_COLUMN[kind]])
    if kind == "framelinvel":  # relative to the reference frame, which turns at ref_ang
        return spatial.quat_rotate_inv(ref_quat, vel - ref_vel - spatial.cross(ref_ang, pos - ref_pos))
    if kind == "frameangvel":
        return spatial.quat_rotate_inv(ref_quat, ang - ref_ang)
    if kind == "gyro":
        return spatial.quat_rotate_inv(quat, ang)
    if kind == "velocimeter":
        return spatial.quat_rotate_inv(quat, vel)
    assert kind == "magnetometer", kind
    return spatial.quat_rotate_inv(quat, lanes.param(sys.sensor_magnetic, 0, 1).unsqueeze(-1).expand_as(pos))


def _subtree_values(sys: System, frames: _Frames, group: SensorGroup) -> torch.Tensor:
    """``subtreecom``, ``subtreelinvel`` or ``subtreeangmom`` ``(3, S, B)`` from the subtree's terms (``System.
    sensor_subtree_*``): their mass-weighted mean position or velocity; or the angular momentum about the subtree's
    COM, each term's spin ``R I R^T w`` plus its mass times its offset from the COM crossed with its velocity
    relative to the COM's."""
    pos, quat, vel, ang = frames.at(sys.sensor_subtree_frame)
    mass = lanes.param(sys.sensor_subtree_mass, 1)
    per_row = _per_row(sys)
    com = _mass_mean(per_row, mass, pos)
    if group.kind == "subtreecom":
        return com.index_select(-2, group.obj)
    com_vel = _mass_mean(per_row, mass, vel)
    if group.kind == "subtreelinvel":
        return com_vel.index_select(-2, group.obj)
    row = sys.sensor_subtree_row
    orbit = mass * spatial.cross(pos - com.index_select(-2, row), vel - com_vel.index_select(-2, row))
    return per_row(_spin(sys, quat, ang) + orbit).index_select(-2, group.obj)


def _per_row(sys: System):
    """Sums over each subtree row's terms: ``(C, K, B) -> (C, R, B)`` (``System.sensor_subtree_*``)."""
    row, rows = sys.sensor_subtree_row, sys.sensor_subtree_contact.shape[0]  # static shapes, no device read
    return lambda x: x.new_zeros(x.shape[0], rows, x.shape[-1]).index_add(-2, row, x)


def _mass_mean(per_row, mass: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Each subtree row's mass-weighted mean of its terms' ``x (3, K, B)``; about the origin for a row without mass
    (a massless subtree)."""
    return per_row(mass * x) / per_row(mass[None])[0].clamp_min(1e-30)


def _spin(sys: System, quat: torch.Tensor, ang: torch.Tensor) -> torch.Tensor:
    """Each subtree term's angular momentum about its own COM, ``R I R^T w`` (principal moments along its frame)."""
    inertia = lanes.param(sys.sensor_subtree_inertia, 1, 1)
    return spatial.quat_rotate(quat, inertia * spatial.quat_rotate_inv(quat, ang))


def _accelerations(sys: System, frames: _Frames, after: _Frames, group: SensorGroup) -> torch.Tensor:
    """``accelerometer``, ``framelinacc`` or ``frameangacc`` ``(3, S, B)``: the mean acceleration of the object's
    frame over the step from ``frames`` to ``after`` (the frames at the next State). The linear ones less gravity,
    as MuJoCo's (its world accelerates at ``-g``), the accelerometer's in its site's frame midway through the step;
    0 for an object fixed to the world, where MuJoCo returns 0 (a dof-less body)."""
    _, quat, vel, ang = frames.at(group.obj)
    _, quat_next, vel_next, ang_next = after.at(group.obj)
    if group.kind == "frameangacc":
        return (ang_next - ang) / sys.timestep
    moving = (sys.sensor_frame_body.index_select(0, group.obj) != sys.num_bodies)[:, None]  # (S, 1)
    acc = torch.where(moving, (vel_next - vel) / sys.timestep - sys.gravity.view(3, 1, 1), 0.0)
    return _in_mean_frame(quat, quat_next, acc) if group.kind == "accelerometer" else acc


def _in_mean_frame(quat: torch.Tensor, quat_next: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """World vectors ``x (3, S, B)``, means over a step, in the frame midway between ``quat`` and ``quat_next``
    (the mean of the two, to second order in the step's turn): a frame spinning at ``w`` turns by ``w dt`` over the
    step, and the step's mean in the frame at its start would be off by half that turn (a box tumbling at 5 rad/s:
    0.02 m/s^2 on its corner's 7.5)."""
    return 0.5 * (spatial.quat_rotate_inv(quat, x) + spatial.quat_rotate_inv(quat_next, x))


def _wrenches(sys: System, frames: _Frames, after: _Frames, contacts: SubstepContacts | None,
              group: SensorGroup) -> torch.Tensor:
    """``force`` or ``torque`` ``(3, S, B)``: MuJoCo's ``cfrc_int`` of the site's body at the site, in its frame.

    Newton-Euler over the subtree's terms (``System.sensor_subtree_*``, its MuJoCo bodies with mass, each rigid
    with its torchsim body): each term's ``m (a - g)`` and the rate of change of its spin ``R I R^T w``, their means
    over the step from ``frames`` to ``after`` (the frames at the next State), the forces' moments about the
    subtree's COM midway through the step; less the mean over the step's substeps of the contact forces on the
    subtree's torchsim bodies (``System.sensor_subtree_contact``; a contact between two of them cancels), the only
    forces MuJoCo counts as external that the loader lets through. The torque moves from the COM to the site by
    ``(com - site) x force``; both in the site's frame midway through the step."""
    pos, quat, vel, ang = frames.at(sys.sensor_subtree_frame)
    pos_next, quat_next, vel_next, ang_next = after.at(sys.sensor_subtree_frame)
    pos = 0.5 * (pos + pos_next)  # the moment arms midway through the step, as the means are
    mass = lanes.param(sys.sensor_subtree_mass, 1)
    per_row = _per_row(sys)
    com = _mass_mean(per_row, mass, pos)
    term_force = mass * ((vel_next - vel) / sys.timestep - sys.gravity.view(3, 1, 1))
    spin_rate = (_spin(sys, quat_next, ang_next) - _spin(sys, quat, ang)) / sys.timestep
    force = per_row(term_force)
    torque = per_row(spin_rate + spatial.cross(pos - com.index_select(-2, sys.sensor_subtree_row), term_force))
    if contacts is not None:
        weights = sys.sensor_subtree_contact.to(force.dtype)  # (R, N + 1), ext-indexed like the contacts' bodies
        share = weights.index_select(1, contacts.body_a)
        if contacts.body_b is not None:  # body b takes the opposite force
            share = share - weights.index_select(1, contacts.body_b)
        share = share[None, :, :, None] / len(contacts.force)  # (1, R, C, 1): the mean over the substeps
        for point, push in zip(contacts.pos, contacts.force):
            on_row = share * push.unsqueeze(1)  # (3, R, C, B)
            force = force - on_row.sum(-2)
            torque = torque - spatial.cross(point.unsqueeze(1) - com.unsqueeze(-2), on_row).sum(-2)
    site_pos, site_quat, _, _ = frames.at(group.obj)
    site_pos_next, site_quat_next, _, _ = after.at(group.obj)
    force, torque, com = (x.index_select(-2, group.ref) for x in (force, torque, com))
    if group.kind == "torque":
        force = torque + spatial.cross(com - 0.5 * (site_pos + site_pos_next), force)
    return _in_mean_frame(site_quat, site_quat_next, force)


def _read(sys: System, state: State, ctrl: torch.Tensor | None, groups: tuple,
          next_state: State | None = None) -> torch.Tensor:
    """``sensordata (nsensordata, B)`` (lanes) with the slots of ``groups`` filled in and the others NaN."""
    batch = state.q.shape[0]
    q, qd = lanes.to_lanes(state.q), lanes.to_lanes(state.qd)
    q_dof, qd_dof = q.index_select(0, sys.dof_qpos), qd.index_select(0, sys.dof_qvel)
    length, velocity = _tendon_coordinates(sys, state, q_dof, qd_dof)
    needs_ctrl = [g.kind for g in groups if g.kind in FORCE_KINDS] + [g.kind for g in groups if g.kind in STEP_KINDS]
    if needs_ctrl:
        if ctrl is None:
            reads = ("read the next step's accelerations, which depend" if needs_ctrl[0] in STEP_KINDS
                     else "read forces that depend")
            raise ValueError(f"the {needs_ctrl[0]} sensors {reads} on the controls: pass ctrl (B, nu)")
        check(sys, "ctrl", ctrl, sys.nu, batch)
    if any(g.kind in FORCE_KINDS for g in groups):
        driving = lanes.to_lanes(ctrl)
        if sys.na:  # static: activated actuators are driven by their activations
            driving = activation.drive(sys, driving, lanes.to_lanes(state.act))[0]
        force = actuators.forces(sys, *actuators.coordinates(sys, q_dof, qd_dof, length, velocity), driving)
    reads_frames = FRAME_KINDS + SUBTREE_KINDS + STEP_KINDS + ("touch",)
    frames = _Frames(sys, state) if any(g.kind in reads_frames for g in groups) else None
    contacts = None
    if any(g.kind == "touch" for g in groups) or (sys.contact_groups and any(g.kind in WRENCH_KINDS for g in groups)):
        next_state, contacts = step_contacts(sys, state, ctrl)  # the step again, for its contacts
    if any(g.kind in STEP_KINDS for g in groups):
        if next_state is None:
            next_state = step(sys, state, ctrl)
        elif next_state.x_pos.shape != state.x_pos.shape:
            raise ValueError(f"next_state's bodies {tuple(next_state.x_pos.shape)} do not match the state's "
                             f"{tuple(state.x_pos.shape)}")
        after = _Frames(sys, next_state)
    data = q.new_full((sys.nsensordata, batch), float("nan"))
    for group in groups:
        kind = group.kind
        if kind in ("jointpos", "jointvel"):
            values = (q if kind == "jointpos" else qd).index_select(0, group.obj)[None]
        elif kind == "ballquat":  # MuJoCo normalises it
            values = spatial.normalize(q.index_select(0, _addresses(group.obj, 4)).view(4, -1, batch))
        elif kind == "ballangvel":
            values = qd.index_select(0, _addresses(group.obj, 3)).view(3, -1, batch)
        elif kind in ("tendonpos", "tendonvel"):
            values = (length if kind == "tendonpos" else velocity).index_select(0, group.obj)[None]
        elif kind in ("actuatorpos", "actuatorvel"):
            values = actuators.coordinates(sys, q_dof, qd_dof, length, velocity)[kind == "actuatorvel"]
            values = values.index_select(0, group.obj)[None]
        elif kind == "actuatorfrc":
            values = force.index_select(0, group.obj)[None]
        elif kind == "jointactuatorfrc":
            values = _joint_actuator_forces(sys, force).index_select(0, group.obj)[None]
        elif kind == "tendonactuatorfrc":
            on_tendon = torch.where(lanes.param(sys.act_tendon >= 0, 1), force, 0.0)
            per_tendon = force.new_zeros(sys.ten_limited.shape[0], batch).index_add(
                0, sys.act_tendon.clamp_min(0), on_tendon)
            values = per_tendon.index_select(0, group.obj)[None]
        elif kind in ("jointlimitpos", "jointlimitvel"):
            values = _limit_values(kind == "jointlimitpos", q_dof, qd_dof, sys.dof_range, sys.dof_margin,
                                   sys.dof_limited).index_select(0, group.obj)[None]
        elif kind in ("tendonlimitpos", "tendonlimitvel"):
            values = _limit_values(kind == "tendonlimitpos", length, velocity,
                                   sys.ten_range, sys.ten_margin, sys.ten_limited).index_select(0, group.obj)[None]
        elif kind == "e_potential":
            values = _potential_energy(sys, state, q_dof, length).expand(1, group.obj.shape[0], batch)
        elif kind == "e_kinetic":
            values = _kinetic_energy(sys, state, qd_dof).expand(1, group.obj.shape[0], batch)
        elif kind in SUBTREE_KINDS:
            values = _subtree_values(sys, frames, group)
        elif kind == "touch":
            values = _touch(sys, mean_contact_forces(sys, contacts), frames, group)
        elif kind in ACC_KINDS:
            values = _accelerations(sys, frames, after, group)
        elif kind in WRENCH_KINDS:
            values = _wrenches(sys, frames, after, contacts, group)
        else:
            values = _frame_values(sys, frames, group)
        data = data.index_copy(0, _addresses(group.adr, values.shape[0]), values.flatten(0, 1))
    cutoff = lanes.param(sys.sensor_cutoff, 1)
    return torch.minimum(torch.maximum(data, -cutoff), cutoff)


def _touch(sys: System, forces: ContactForces, frames: _Frames, group: SensorGroup) -> torch.Tensor:
    """MuJoCo's touch sensors ``(1, S, B)``: the normal forces of the contacts on each site's body whose point lies
    in the site's zone, or whose ray from the point away from that body meets it (as ``mj_sensorAcc``)."""
    pos, normal, force = (lanes.to_lanes(x, 1).unsqueeze(1) for x in (forces.pos, forces.normal, forces.force))
    push = spatial.dot(force, normal)  # (1, C, B): the normal force on body a, > 0 pushing
    world = sys.num_bodies  # contact_forces names the world -1, the sensor frames by its ext index
    body_a, body_b = (torch.where(b < 0, world, b) for b in (forces.body_a, forces.body_b))
    site_pos, site_quat, _, _ = (x.unsqueeze(2) for x in frames.at(group.obj))  # (3|4, S, 1, B)
    site_body = sys.sensor_frame_body.index_select(0, group.obj)[:, None]  # (S, 1)
    on_a, on_b = site_body == body_a, site_body == body_b  # (S, C)
    away = torch.where(on_a, -1.0, 1.0).to(normal.dtype)[..., None] * normal  # normal points from body b to a
    origin = spatial.quat_rotate_inv(site_quat, pos - site_pos)  # (3, S, C, B), in the site's frame
    direction = spatial.quat_rotate_inv(site_quat, away.expand_as(origin))
    size = lanes.param(sys.sensor_touch_size.index_select(0, group.ref), 1, 1).unsqueeze(-1)  # (3, S, 1, 1)
    shape = sys.sensor_touch_shape.index_select(0, group.ref)[:, None, None]  # (S, 1, 1)
    in_zone = torch.zeros_like(push, dtype=torch.bool).expand_as(origin[0])
    for name in ("sphere", "capsule", "ellipsoid", "cylinder", "box"):
        if bool((shape == raycast.CODE[name]).any()):
            meets = _inside(name, origin, size) | torch.isfinite(raycast.HIT[name](origin, direction, size, 0.0,
                                                                                  float("inf")))
            in_zone = in_zone | ((shape == raycast.CODE[name]) & meets)
    counted = (on_a | on_b)[..., None] & in_zone & forces.active.T[None] & (push > 0)
    return torch.where(counted, push, 0.0).sum(-2)[None]


def _inside(name: str, o: torch.Tensor, size: torch.Tensor) -> torch.Tensor:
    """Whether local points ``o (3, ...)`` lie in a site of shape ``name`` and MuJoCo ``size (3, ...)``."""
    if name == "sphere":
        return spatial.dot(o, o) <= size[0] ** 2
    if name == "ellipsoid":
        return ((o / size) ** 2).sum(0) <= 1.0
    if name == "box":
        return (o.abs() <= size).all(0)
    radial = o[0] ** 2 + o[1] ** 2
    if name == "cylinder":
        return (radial <= size[0] ** 2) & (o[2].abs() <= size[1])
    beyond = (o[2].abs() - size[1]).clamp_min(0.0)  # capsule: the distance to its segment
    return radial + beyond ** 2 <= size[0] ** 2


def _limit_values(position: bool, x: torch.Tensor, rate: torch.Tensor, bounds: torch.Tensor, margin: torch.Tensor,
                  limited: torch.Tensor) -> torch.Tensor:
    """MuJoCo's limit sensors ``(R, B)`` of coordinates ``x`` and rates ``rate (R, B)`` (dofs or tendons) with the
    System fields ``bounds (R, 2)``, ``margin (R,)`` and ``limited (R,)``: of MuJoCo's limit constraint rows, the
    first side within its margin (the lower before the upper) gives its distance less the margin (``position``) or
    its rate (positive moving away from that side); 0 where neither side is within its margin."""
    lo, hi = lanes.param(bounds, 1, 1).unbind(0)
    margin, limited = lanes.param(margin, 1), lanes.param(limited, 1)
    below, above = x - lo, hi - x
    lower, upper = limited & (below < margin), limited & (above < margin)
    at_lower, at_upper = (below - margin, above - margin) if position else (rate, -rate)
    return torch.where(lower, at_lower, torch.where(upper, at_upper, 0.0))


def _tendon_coordinates(sys: System, state: State, q: torch.Tensor, qd: torch.Tensor):
    """Every tendon's length and rate ``(T, B)``: fixed ones' from the dof coordinates and rates ``q, qd (D, B)``,
    spatial ones' along their paths at the State's bodies (``torchsim.tendon_paths``)."""
    length, velocity = tendons.lengths(sys, q), tendons.lengths(sys, qd)
    if not sys.ten_spatial:  # static
        return length, velocity
    path = tendon_paths.paths(sys, with_world(*to_lanes_state(state)[:4]))
    return length + path.length, velocity + path.velocity


def _potential_energy(sys: System, state: State, q: torch.Tensor, length: torch.Tensor) -> torch.Tensor:
    """MuJoCo's ``e_potential`` ``(1, B)`` [J] at dof coordinates ``q (D, B)`` and tendon lengths ``length (T, B)``:
    ``-m g . x`` of every body, and the joint and tendon springs' ``k x^2 / 2`` (a tendon's ``x`` beyond its dead
    band)."""
    x_pos = lanes.to_lanes(state.x_pos, 1)
    gravity = sys.gravity.view(3, 1, 1)
    weight = -(lanes.param(sys.body_mass, 1) * spatial.dot(gravity, x_pos)).sum(0, keepdim=True)
    stretch = q - lanes.param(sys.dof_springref, 1)
    joints = 0.5 * (lanes.param(sys.dof_stiffness, 1) * stretch * stretch).sum(0, keepdim=True)
    energy = sys.sensor_static_potential + weight + joints
    if sys.ten_springs:  # static: a model without tendon springs has none to add
        lo, hi = lanes.param(sys.ten_lengthspring, 2).unbind(-2)
        stretch = torch.clamp(length - hi, min=0.0) + torch.clamp(length - lo, max=0.0)
        energy = energy + 0.5 * (lanes.param(sys.ten_stiffness, 1) * stretch * stretch).sum(0, keepdim=True)
    return energy


def _kinetic_energy(sys: System, state: State, qd: torch.Tensor) -> torch.Tensor:
    """MuJoCo's ``e_kinetic`` ``(1, B)`` [J], ``qvel M qvel / 2``, from the bodies' COM and angular velocities and
    the dofs' rates ``qd (D, B)`` (their armature)."""
    quat, vel, ang = (lanes.to_lanes(x, 1) for x in (state.x_quat, state.xd_vel, state.xd_ang))
    ang_body = spatial.quat_rotate_inv(quat, ang)
    spin = spatial.dot(ang_body, spatial.matvec(lanes.param(sys.body_inertia, 1, 2), ang_body))
    bodies = (lanes.param(sys.body_mass, 1) * spatial.dot(vel, vel) + spin).sum(0, keepdim=True)
    rotors = (lanes.param(sys.dof_armature, 1) * qd * qd).sum(0, keepdim=True)
    return 0.5 * (bodies + rotors)


def _joint_actuator_forces(sys: System, force: torch.Tensor) -> torch.Tensor:
    """MuJoCo's ``qfrc_actuator`` on the hinge and slide dofs ``(D, B)`` of actuator forces ``(U, B)``: ``gear *
    force`` on a joint actuator's dof, and through each tendon's coefficients for tendon actuators."""
    geared = lanes.param(sys.act_gear, 1) * force
    tau = force.new_zeros(sys.dof_qpos.shape[0], force.shape[-1])
    if not sys.act_on_tendons:  # static: every actuator acts on its dof
        return tau.index_add(0, sys.act_dof, geared)
    on_tendon = lanes.param(sys.act_tendon >= 0, 1)
    tau = tau.index_add(0, sys.act_dof.clamp_min(0), torch.where(on_tendon, 0.0, geared))
    per_tendon = force.new_zeros(sys.ten_limited.shape[0], force.shape[-1]).index_add(
        0, sys.act_tendon.clamp_min(0), torch.where(on_tendon, geared, 0.0))
    return tendons.add_to_dofs(sys, tau, per_tendon)
