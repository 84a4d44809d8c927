"""``System``: the static model as tensors, built once by a loader and never branched on at step time."""

import dataclasses
from typing import NamedTuple

import torch

#: Contact points a pair of each kind evaluates per substep (a box on a plane: its 8 corners).
POINTS_PER_PAIR = {
    "sphere_plane": 1, "capsule_plane": 2, "box_plane": 8, "sphere_sphere": 1, "sphere_capsule": 1,
    "capsule_capsule": 1, "sphere_box": 1, "capsule_box": 3, "box_box": 16,
}


class ContactGroup(NamedTuple):
    """All candidate geom pairs of one shape combination, evaluated together every substep.

    Attributes:
        kind: shape pair, e.g. ``"plane_sphere"``; geom ``a`` is the first shape named, ``b`` the second.
        geom_a, geom_b: (P,) geom indices.
        friction: (P,) or (B, P) sliding friction coefficient of the pair.
        margin: (P,) distance at which contact activates [m] (MuJoCo ``margin``).
    """

    kind: str
    geom_a: torch.Tensor
    geom_b: torch.Tensor
    friction: torch.Tensor
    margin: torch.Tensor


#: The *batchable* fields of ``System`` and their rank without a batch dimension (contact groups' friction and
#: margin are batchable too, rank 1).
BATCHABLE_RANK = {"body_mass": 1, "body_inertia": 3, "dof_damping": 1, "dof_armature": 1, "dof_stiffness": 1,
                  "dof_springref": 1, "act_gear": 1, "act_gain": 1, "act_bias": 2}


@dataclasses.dataclass(frozen=True)
class System:
    """A rigid-body model in maximal coordinates. ``N`` bodies, ``J`` constrained joints, ``D`` hinge/slide dofs,
    ``U`` actuators, ``G`` geoms. Index ``N`` ("ext" indexing) denotes the static world.

    Physical parameters marked *batchable* may carry a leading ``(B,)`` dimension so every env can differ
    (domain randomisation) without rebuilding anything; the step only indexes their trailing dimensions.

    Bodies:
        body_mass: (N,) [kg], batchable.  body_inertia: (N, 3, 3) about the COM in the body frame, batchable.
        body_ipos: (N, 3) COM in the body frame.  body_parent: (N,) ext index of the parent body.
        body_hinge_body, body_hinge_dof, body_hinge_sign: (P,) the (body, hinge dof) incidences, grouped by body,
        sign +1 where the body is the hinge's child and -1 its parent; body_hinge_pairs: (Q, 2) the ordered pairs
        of incidences on a common body. The sparsity of the hinges' coupling through the bodies.
    Joints (one per non-free body; a body's hinges/slides/ball relative to its parent form one joint):
        jnt_child, jnt_parent: (J,).  jnt_anchor_child: (J, 3) anchor from the child COM, child frame.
        jnt_anchor_parent: (J, 3) anchor at q = 0 from the parent COM, parent frame (world frame for the world).
        jnt_quat0: (J, 4) child frame in the parent frame at q = 0.
        jnt_axes: (J, 3, 3) hinge axes a1..a3 (child frame); unused rows hold padding axes completing a basis.
            The rows are orthonormal (the loader requires a joint's hinges to be mutually orthogonal).
        jnt_mode: (J, 5) one-hot angular mode: [weld, 1 hinge, 2 hinges, 3 hinges, ball].
        jnt_a2_sign: (J,) handedness a1 . (a2 x a3) of 3-hinge joints (1 otherwise).
        jnt_slide_axes: (J, 3, 3) slide axes (rows, zero frame; unused rows zero).
        jnt_slide_pinv: (J, 3, 3) pseudo-inverse mapping an anchor offset (zero frame) to slide coordinates.
        jnt_lin_proj: (J, 3, 3) projector onto the constrained translation directions (zero frame).
        jnt_colors: index tensors partitioning the joints so that no two joints of a colour share a body.
        jnt_levels: index tensors of the joints at each tree depth (free bodies are roots).
        jnt_slot_dof: (J, 6) dof index of each joint slot, -1 where the slot is not a dof.
        jnt_kinds: 5 bools, which angular modes occur; jnt_has_slides: whether any slide occurs (static structure
        that lets the step skip work for joint kinds the model lacks).
    Dofs (hinge and slide dofs of constrained joints):
        dof_flat: (D,) index into a joint's 6 coordinate slots (3 slides, then 3 hinges), flattened as j*6+slot.
        dof_is_hinge: (D,) bool.  dof_qpos, dof_qvel: (D,) addresses in qpos/qvel.
        dof_limited: (D,) bool.  dof_range: (D, 2).  dof_ref: (D,) MuJoCo qpos0 (the coordinate of the zero frame).
        dof_damping, dof_armature, dof_stiffness, dof_springref: (D,), batchable.
        ball_joint, ball_qpos, ball_qvel: (nball,) ball joints and their addresses.
        free_body, free_qpos, free_qvel: (nfree,) free-floating bodies and their addresses.
    Actuators (MuJoCo ``gaintype=fixed``, ``biastype=none|affine``, joint transmission):
        act_dof: (U,) dof index.  act_gear, act_gain: (U,), batchable.  act_bias: (U, 3), batchable.
        act_ctrl_range, act_force_range: (U, 2); act_ctrl_limited, act_force_limited: (U,) bool.
    Geometry and contacts:
        geom_body: (G,) ext body index.  geom_pos, geom_quat: (G, 3), (G, 4) from the body COM in the body frame
        (world frame for static geoms).  geom_size: (G, 3) MuJoCo sizes.  contact_groups: one per shape pair.
    MuJoCo bodies (for poses of fused bodies, e.g. rendering): mjbody_body (nbody,) ext index;
        mjbody_pos, mjbody_quat: frame offset of each MuJoCo body in its fused body's frame.
    """

    # sizes and options
    nq: int
    nv: int
    nu: int
    timestep: float
    substeps: int
    method: str
    gravity: torch.Tensor
    q0: torch.Tensor
    # solver parameters (see ``torchsim.io_mjcf.load_mjcf`` for their meaning and defaults)
    joint_stiffness: float
    joint_damping: float
    contact_timeconst: float
    xpbd_iterations: int
    max_speed: float
    max_distance: float
    # bodies
    body_mass: torch.Tensor
    body_inertia: torch.Tensor
    body_ipos: torch.Tensor
    body_parent: torch.Tensor
    body_names: tuple
    body_hinge_body: torch.Tensor
    body_hinge_dof: torch.Tensor
    body_hinge_sign: torch.Tensor
    body_hinge_pairs: torch.Tensor
    # joints
    jnt_child: torch.Tensor
    jnt_parent: torch.Tensor
    jnt_anchor_child: torch.Tensor
    jnt_anchor_parent: torch.Tensor
    jnt_quat0: torch.Tensor
    jnt_axes: torch.Tensor
    jnt_mode: torch.Tensor
    jnt_a2_sign: torch.Tensor
    jnt_slide_axes: torch.Tensor
    jnt_slide_pinv: torch.Tensor
    jnt_lin_proj: torch.Tensor
    jnt_colors: tuple
    jnt_levels: tuple
    jnt_slot_dof: torch.Tensor
    jnt_kinds: tuple
    jnt_has_slides: bool
    # dofs
    dof_flat: torch.Tensor
    dof_is_hinge: torch.Tensor
    dof_qpos: torch.Tensor
    dof_qvel: torch.Tensor
    dof_limited: torch.Tensor
    dof_range: torch.Tensor
    dof_damping: torch.Tensor
    dof_armature: torch.Tensor
    dof_stiffness: torch.Tensor
    dof_springref: torch.Tensor
    dof_ref: torch.Tensor
    ball_joint: torch.Tensor
    ball_qpos: torch.Tensor
    ball_qvel: torch.Tensor
    free_body: torch.Tensor
    free_qpos: torch.Tensor
    free_qvel: torch.Tensor
    # actuators
    act_dof: torch.Tensor
    act_gear: torch.Tensor
    act_gain: torch.Tensor
    act_bias: torch.Tensor
    act_ctrl_range: torch.Tensor
    act_ctrl_limited: torch.Tensor
    act_force_range: torch.Tensor
    act_force_limited: torch.Tensor
    # geometry
    geom_body: torch.Tensor
    geom_pos: torch.Tensor
    geom_quat: torch.Tensor
    geom_size: torch.Tensor
    contact_groups: tuple
    # MuJoCo body frames
    mjbody_body: torch.Tensor
    mjbody_pos: torch.Tensor
    mjbody_quat: torch.Tensor

    @property
    def substep_timestep(self) -> float:
        """The length of one substep [s]: ``timestep / substeps``."""
        return self.timestep / self.substeps

    @property
    def num_bodies(self) -> int:
        return self.body_ipos.shape[0]

    @property
    def num_contacts(self) -> int:
        """Contact points evaluated per env and substep (a box-plane pair counts its 8 corners)."""
        return sum(POINTS_PER_PAIR[g.kind] * g.geom_a.shape[0] for g in self.contact_groups)

    @property
    def num_contact_pairs(self) -> int:
        return sum(g.geom_a.shape[0] for g in self.contact_groups)

    def leaves(self):
        """Every value the System holds, in field order, its tuples (e.g. the contact groups) flattened."""
        return _leaves(tuple(getattr(self, f.name) for f in dataclasses.fields(self)))

    @property
    def requires_grad(self) -> bool:
        """Whether any parameter tensor requires grad (e.g. masses being fitted)."""
        return any(isinstance(x, torch.Tensor) and x.requires_grad for x in self.leaves())

    def batchable(self) -> list[tuple[tuple, int]]:
        """Every batchable parameter, as ``(where, rank)``: ``where`` is ``(name,)`` for a field of
        ``BATCHABLE_RANK`` or ``(group, name)`` for a contact group's ``friction`` or ``margin``; ``rank`` its rank
        without a per-env dimension."""
        return [((name,), rank) for name, rank in BATCHABLE_RANK.items()] + [
            ((i, name), 1) for i in range(len(self.contact_groups)) for name in ("friction", "margin")]

    def parameter(self, where: tuple) -> torch.Tensor:
        """The batchable parameter at ``where`` (:meth:`batchable`)."""
        return getattr(self, where[0]) if len(where) == 1 else getattr(self.contact_groups[where[0]], where[1])

    def with_parameters(self, wheres: list[tuple], values: list[torch.Tensor]) -> "System":
        """This System with the batchable parameters at ``wheres`` replaced by ``values``."""
        fields = {w[0]: v for w, v in zip(wheres, values) if len(w) == 1}
        groups = list(self.contact_groups)
        for w, v in zip(wheres, values):
            if len(w) == 2:
                groups[w[0]] = groups[w[0]]._replace(**{w[1]: v})
        return dataclasses.replace(self, contact_groups=tuple(groups), **fields)

    def per_env_parameters(self) -> list[tuple]:
        """Where the System holds per-env parameters: the batchable ones with a leading per-env dimension."""
        return [where for where, rank in self.batchable() if self.parameter(where).ndim > rank]

    @property
    def batched(self) -> bool:
        """Whether some batchable parameter carries a leading per-env dimension (``BATCHABLE_RANK``)."""
        return bool(self.per_env_parameters())

    @property
    def dtype(self) -> torch.dtype:
        return self.body_ipos.dtype

    @property
    def device(self) -> torch.device:
        return self.body_ipos.device

    def to(self, device=None, dtype=None) -> "System":
        """Copy to ``device`` and/or floating ``dtype`` (integer and bool index tensors keep their dtype)."""

        def move(x):
            if isinstance(x, torch.Tensor):
                return x.to(device=device, dtype=dtype if x.is_floating_point() else None)
            if isinstance(x, ContactGroup):
                return ContactGroup(x.kind, *(move(t) for t in x[1:]))
            if isinstance(x, tuple):
                return tuple(move(t) for t in x)
            return x

        return dataclasses.replace(self, **{f.name: move(getattr(self, f.name)) for f in dataclasses.fields(self)})

    def replace(self, **changes) -> "System":
        """A copy with some fields replaced, e.g. ``sys.replace(body_mass=mass_per_env)`` for randomisation."""
        return dataclasses.replace(self, **changes)


def _leaves(x):
    """The values in ``x``, a value or a (nested) tuple of them; a tensor is one value."""
    if isinstance(x, tuple):
        for item in x:
            yield from _leaves(item)
    else:
        yield x
