"""The record each solution method module ends with (``torchsim.methods``)."""

from typing import Callable, NamedTuple


class Method(NamedTuple):
    """What the engine needs of a solution method.

    Attributes:
        name: the ``method`` argument of ``torchsim.load_mjcf``.
        step_terms: ``(sys, bodies, q, h) -> terms``: what a step's substeps share, built from the poses at the
            step's start and their coordinates ``q (nq, B)`` (``h``: the substep length [s],
            ``System.substep_timestep``).
        substep: ``(sys, bodies, ctrl, terms, h) -> bodies``: one substep, lanes layout.
        default_substep_timestep: the substep length [s] ``load_mjcf`` aims at (substeps = ceil(timestep / it)).
        contact_forces: ``(sys, bodies, ctrl, terms, h) -> (contacts, force (3, C, B))``: the force each contact
            point puts on its body a over the first substep from ``bodies`` (``torchsim.contact_forces``); None
            where the method does not read them out.
    """

    name: str
    step_terms: Callable
    substep: Callable
    default_substep_timestep: float
    contact_forces: Callable | None = None
