"""The contact forces of a state, as MuJoCo's ``mj_contactForce`` reads them after ``mj_forward``: what the
contacts push with over the next substep from the state, under controls ``ctrl``.

    forces = torchsim.contact_forces(sys, state, ctrl)
    forces.force[forces.active]     # (K, 3) world-frame force on each active point's body a [N]

The force is the substep's contact impulse over its length ``h``, the same computation ``torchsim.step`` applies
(``methods.spring.contact_forces``), so it is the force the step uses, not a separate estimate. A body at rest
on a plane holds its weight up through them; touch and force sensors can be built on them.
"""

from typing import NamedTuple

import torch

from torchsim import lanes
from torchsim.methods import METHODS
from torchsim.pipeline import check, to_lanes
from torchsim.state import State
from torchsim.system import System


class ContactForces(NamedTuple):
    """Every contact point of a state's pairs, ``C`` per env, batch first.

    Attributes:
        pos: (B, C, 3) world contact point [m].
        normal: (B, C, 3) unit normal from body b towards body a.
        depth: (B, C) penetration [m]; the point pushes where it is positive.
        active: (B, C) bool, ``depth > 0``.
        force: (B, C, 3) world-frame force on body a [N]: normal push plus friction. Body b takes its opposite,
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


def contact_forces(sys: System, state: State, ctrl: torch.Tensor) -> ContactForces:
    """The contact forces the next substep from ``state`` applies under ``ctrl (B, nu)`` (see the module)."""
    check(sys, "ctrl", ctrl, sys.nu, state.x_pos.shape[0])
    method = METHODS[sys.method]
    if method.contact_forces is None:
        raise NotImplementedError(f"contact forces are read out for the spring method only, not {sys.method!r}")
    bodies, ctrl_lanes = to_lanes(state, ctrl)
    h = sys.substep_timestep
    terms = method.step_terms(sys, bodies, lanes.to_lanes(state.q), h)
    con, force = method.contact_forces(sys, bodies, ctrl_lanes, terms, h)
    world = sys.num_bodies  # the ext index to_lanes gives the static world (after the moving bodies)
    body_a = torch.where(con.body_a == world, -1, con.body_a)
    body_b = torch.full_like(body_a, -1) if con.body_b is None else torch.where(con.body_b == world, -1, con.body_b)
    return ContactForces(lanes.from_lanes(con.pos, 1), lanes.from_lanes(con.normal, 1), lanes.from_lanes(con.depth),
                         lanes.from_lanes(con.depth) > 0, lanes.from_lanes(force, 1), body_a, body_b)
