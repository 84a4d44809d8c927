"""The contact forces of a state, as MuJoCo's ``mj_contactForce`` reads them after ``mj_forward``: what the
contacts push with over the next step from the state, under controls ``ctrl``.

    forces = torchsim.contact_forces(sys, state, ctrl)
    forces.force[forces.active]     # (K, 3) world-frame force on each active point's body a [N]

Each point's force is the mean over the step's substeps of its contact impulse over the substep's length ``h``, the
same computation ``torchsim.step`` applies (``methods.spring.contact_forces``), so it is the force the step uses,
not a separate estimate. The mean, not the first substep's: at rest a foot's friction stops each substep's slip and
alternates in direction from one substep to the next (the resting Ant's feet: 1.37 N, 35 degrees off the leg's
plane, turning each hip by 0.48 N m one substep and -0.48 N m the next), where its mean over the step is MuJoCo's
(``tests/test_contact_forces.py``). A body at rest on a plane holds its weight up through them; touch and force
sensors are built on them (``torchsim.sensors``).
"""

from typing import NamedTuple

import torch

from torchsim import lanes
from torchsim.methods import METHODS
from torchsim.pipeline import check, run_substeps
from torchsim.state import State
from torchsim.system import System


class ContactForces(NamedTuple):
    """Every contact point of a state's pairs, ``C`` per env, batch first.

    Attributes:
        pos: (B, C, 3) world contact point at the state [m].
        normal: (B, C, 3) unit normal from body b towards body a, at the state.
        depth: (B, C) penetration at the state [m]; the point pushes where it is positive.
        active: (B, C) bool, the point pushes in one of the step's substeps at least (``depth > 0`` there).
        force: (B, C, 3) world-frame force on body a [N], the mean over the step's substeps (zero in those where
            the point does not push): normal push plus friction. Body b takes its opposite,
            but for the impulse contact model's per-body averaging, which can share a point's impulse unequally
            between two moving bodies (``methods.spring.contact_impulse_terms``).
        body_a, body_b: (C,) the bodies' indices in the State's body order (``-1``: the static world).
    """

    pos: torch.Tensor
    normal: torch.Tensor
    depth: torch.Tensor
    active: torch.Tensor
    force: torch.Tensor
    body_a: torch.Tensor
    body_b: torch.Tensor


class SubstepContacts(NamedTuple):
    """The contacts of each substep of a step, lanes layout, as the spring method applies them: per substep the
    points ``pos (3, C, B)``, unit normals ``normal (3, C, B)``, depths ``depth (C, B)`` and the force ``(3, C, B)``
    on body a over the substep [N] (zero where the point does not push; body b takes its opposite); ext bodies
    ``body_a, body_b (C,)`` (``body_b`` None where every pair is against the static world)."""

    pos: list
    normal: list
    depth: list
    force: list
    body_a: torch.Tensor
    body_b: torch.Tensor | None


def step_contacts(sys: System, state: State, ctrl: torch.Tensor) -> tuple[State, SubstepContacts]:
    """``torchsim.step``'s next State, by the same outline (``pipeline.run_substeps``), and the contacts each of its
    substeps applies."""
    method = METHODS[sys.method]
    if method.contact_forces is None:
        raise NotImplementedError(f"contact forces are read out for the spring method only, not {sys.method!r}")
    contacts = SubstepContacts([], [], [], [], None, None)
    body_ab = []

    def substep(sys, bodies, ctrl, terms, h):
        con, push = method.contact_forces(sys, bodies, ctrl, terms, h)
        pushing = torch.where(con.depth > 0, push, 0.0)
        for recorded, value in zip(contacts[:4], (con.pos, con.normal, con.depth, pushing)):
            recorded.append(value)
        body_ab[:] = [con.body_a, con.body_b]
        return method.substep(sys, bodies, ctrl, terms, h)

    after = run_substeps(sys, state, ctrl, substep=substep)
    return after, contacts._replace(body_a=body_ab[0], body_b=body_ab[1])


def mean_contact_forces(sys: System, contacts: SubstepContacts) -> ContactForces:
    """The step's contact forces (the module): each point where it is at the step's start, its force the mean over
    the substeps; active where it pushes in any substep."""
    force = torch.stack(contacts.force).mean(0)
    pushes = torch.stack(contacts.depth).gt(0).any(0)
    world = sys.num_bodies  # the ext index to_lanes gives the static world (after the moving bodies)
    body_a = torch.where(contacts.body_a == world, -1, contacts.body_a)
    body_b = (torch.full_like(body_a, -1) if contacts.body_b is None
              else torch.where(contacts.body_b == world, -1, contacts.body_b))
    return ContactForces(lanes.from_lanes(contacts.pos[0], 1), lanes.from_lanes(contacts.normal[0], 1),
                         lanes.from_lanes(contacts.depth[0]), lanes.from_lanes(pushes), lanes.from_lanes(force, 1),
                         body_a, body_b)


def contact_forces(sys: System, state: State, ctrl: torch.Tensor) -> ContactForces:
    """The contact forces of the next step from ``state`` under ``ctrl (B, nu)`` (the module); it steps once."""
    check(sys, "ctrl", ctrl, sys.nu, state.x_pos.shape[0])
    return mean_contact_forces(sys, step_contacts(sys, state, ctrl)[1])
