"""``System``: the static model as tensors, built once by a loader and never branched on at step time."""

import dataclasses
from typing import NamedTuple

import torch

#: Contact points a pair of each kind evaluates per substep (a box on a plane: its 8 corners).
POINTS_PER_PAIR = {
    "sphere_plane": 1, "capsule_plane": 2, "box_plane": 8, "sphere_sphere": 1, "sphere_capsule": 1,
    "capsule_capsule": 1, "sphere_box": 1, "capsule_box": 3, "box_box": 16,
    "ellipsoid_plane": 1, "cylinder_plane": 8, "sphere_ellipsoid": 1, "sphere_cylinder": 1, "capsule_ellipsoid": 3,
    "capsule_cylinder": 3, "ellipsoid_ellipsoid": 1, "cylinder_cylinder": 17, "ellipsoid_box": 1,
    "cylinder_box": 29, "ellipsoid_cylinder": 1,
    # height fields: the deepest candidates kept per pair (``torchsim.collision_hfield``)
    "sphere_hfield": 4, "capsule_hfield": 10, "box_hfield": 12, "ellipsoid_hfield": 6, "cylinder_hfield": 12,
}


#: Contact points per pair of the kinds with a mesh (``torchsim.collision_mesh``), as (fixed, per vertex of the
#: model's largest hull): a mesh pair tests every vertex of its (padded) hulls.
MESH_POINTS_PER_PAIR = {"mesh_plane": (0, 1), "sphere_mesh": (1, 0), "capsule_mesh": (3, 0), "box_mesh": (9, 1),
                        "mesh_mesh": (1, 2), "cylinder_mesh": (9, 1), "ellipsoid_mesh": (1, 0)}


def points_per_pair(kind: str, hull_vertices: int) -> int:
    """Contact points a pair of ``kind`` evaluates per substep, in a model whose largest hull has ``hull_vertices``
    vertices (``System.geom_hull_vert``)."""
    if kind in MESH_POINTS_PER_PAIR:
        fixed, per_vertex = MESH_POINTS_PER_PAIR[kind]
        return fixed + per_vertex * hull_vertices
    return POINTS_PER_PAIR[kind]


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


class SensorGroup(NamedTuple):
    """All computed sensors of one MuJoCo type, read together (``torchsim.sensors``).

    Attributes:
        kind: the sensor type's MJCF name, e.g. ``"framepos"``.
        adr: (S,) each sensor's first address in ``sensordata``.
        obj: (S,) what each reads, by kind: a qpos address (``jointpos``, ``ballquat``), a qvel address
            (``jointvel``, ``ballangvel``), a tendon, an actuator, a dof (``jointactuatorfrc``), a sensor frame
            (frame sensors, ``gyro``, ``velocimeter``, ``magnetometer``, ``framelinacc``, ``frameangacc``; the site
            of a ``touch``, ``accelerometer``, ``force`` or ``torque`` sensor) or a subtree row (``subtreecom``,
            ``subtreelinvel``, ``subtreeangmom``).
        ref: (S,) the sensor frame of a frame sensor's reference (0, the world, where it has none); a touch
            sensor's zone (``System.sensor_touch_size``); the subtree row of a force or torque sensor's site's body;
            -1 for others.
    """

    kind: str
    adr: torch.Tensor
    obj: torch.Tensor
    ref: torch.Tensor


#: The *batchable* fields of ``System`` and their rank without a batch dimension (contact groups' friction and
#: margin are batchable too, rank 1).
BATCHABLE_RANK = {"body_mass": 1, "body_inertia": 3, "dof_damping": 1, "dof_armature": 1, "dof_stiffness": 1,
                  "dof_springref": 1, "dof_frictionloss": 1, "act_gear": 1, "act_gain": 1, "act_bias": 2,
                  "mocap_pos": 2, "mocap_quat": 2}


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
        jnt_anchor_offset: (J, 3) [m] for 2 hinges at different anchors, the second anchor minus the first in
            components along a1..a3 (jnt_axes); zero otherwise. jnt_anchor_child is the second anchor, and the
            parent anchor (the first) turns by this offset with the first hinge (``torchsim.hinge_anchors``).
        jnt_general: (J,) bool, 2 hinges on non-orthogonal axes or 3 hinges not sharing one anchor and orthogonal
            axes: their angles and anchors are composed in general form (``kinematics.joint_frames``).
        jnt_anchor_steps: (J, 2, 3) [m] for general joints, the second anchor minus the first (parent frame, as at
            q = 0) and the third minus the second (child frame); zero otherwise (``hinge_anchors.chain_offset``).
        jnt_quat0: (J, 4) child frame in the parent frame at q = 0.
        jnt_axes: (J, 3, 3) hinge axes a1..a3 (child frame); unused rows hold padding axes completing a basis.
            The rows are orthonormal except for general joints (``jnt_general``), whose rows are their unit axes.
        jnt_mode: (J, 5) one-hot angular mode: [weld, 1 hinge, 2 hinges, 3 hinges, ball].
        jnt_a2_sign: (J,) handedness a1 . (a2 x a3) of 3-hinge joints (1 otherwise).
        jnt_slide_axes: (J, 3, 3) slide axes (rows, zero frame; unused rows zero).
        jnt_slide_pinv: (J, 3, 3) pseudo-inverse mapping an anchor offset (zero frame) to slide coordinates.
        jnt_lin_proj: (J, 3, 3) projector onto the constrained translation directions (zero frame).
        jnt_colors: index tensors partitioning the joints so that no two joints of a colour share a body.
        jnt_levels: index tensors of the joints at each tree depth (free bodies are roots).
        jnt_slot_dof: (J, 6) dof index of each joint slot, -1 where the slot is not a dof.
        jnt_kinds: 5 bools, which angular modes occur; jnt_has_slides: whether any slide occurs; jnt_has_offsets:
        whether any joint has a nonzero jnt_anchor_offset or jnt_anchor_steps; jnt_has_general: whether any joint is
        general (static structure that lets the step skip work for joint kinds the model lacks).
    Dofs (hinge and slide dofs of constrained joints):
        dof_flat: (D,) index into a joint's 6 coordinate slots (3 slides, then 3 hinges), flattened as j*6+slot.
        dof_is_hinge: (D,) bool.  dof_qpos, dof_qvel: (D,) addresses in qpos/qvel.
        dof_limited: (D,) bool.  dof_range: (D, 2).  dof_ref: (D,) MuJoCo qpos0 (the coordinate of the zero frame).
        dof_limit_gains: (D, 2) MuJoCo's reference-acceleration gains ``K`` [1/s^2], ``B`` [1/s] from the joint's
        ``solref``.  dof_solimp: (D, 5) the joint's ``solimp``.  dof_margin: (D,) [rad | m] the limit's ``margin``.
        dof_invweight: (D,) MuJoCo's ``dof_invweight0`` (its limit regulariser's scale).  dof_limits: whether any
        dof is limited (static structure: a model without limits does no limit work; ``joint_space.limit_rows``);
        dof_solimp_square: whether every solimp ``power`` is 2 (static: its impedance needs no exp and log).
        dof_damping, dof_armature, dof_stiffness, dof_springref: (D,), batchable.
        dof_frictionloss: (D,) largest dry-friction force [N m | N] (MuJoCo ``frictionloss``), batchable; which dofs
        have friction is static structure decided at load: dof_friction_hinges (F,) the hinge dofs with nonzero
        frictionloss, dof_friction_slides whether any slide dof has it (a per-env value elsewhere is ignored).
        ball_joint, ball_qpos, ball_qvel: (nball,) ball joints and their addresses.
        free_body, free_qpos, free_qvel: (nfree,) free-floating bodies and their addresses.
        ball_damping [N m s], ball_armature [kg m^2], ball_stiffness [N m/rad]: (nball,) each ball joint's (one
        value for its 3 dofs, as MJCF sets them); ball_spring: (nball, 4) the quaternion its spring pulls towards
        (MuJoCo's ``qpos_spring``).  free_damping, free_armature: (nfree,) each free joint's, on all 6 dofs (MuJoCo's:
        linear ones on the velocity of the body frame's origin, world frame; angular ones on the angular velocity).
        free_origin: (nfree, 3) that origin from the body's COM, body frame [m].  root_passive: whether any ball
        joint or free body has damping, armature or stiffness (static: a model without skips their work,
        ``joint_space.root_rate_solve``).
    Actuators (MuJoCo ``gaintype`` fixed or muscle, ``biastype`` none, affine or muscle; joint, tendon or site
    transmission; ``torchsim.actuators``):
        act_dof: (U,) dof index, -1 for tendon and site transmission.  act_gear, act_gain: (U,), batchable.
        act_bias: (U, 3), batchable.
        act_ctrl_range, act_force_range: (U, 2); act_ctrl_limited, act_force_limited: (U,) bool.
        act_tendon: (U,) tendon of an actuator with tendon transmission (its act_dof is -1), -1 for joint ones.
        act_adr: (U,) the actuator's activation in ``State.act`` (MuJoCo ``actuator_actadr``), -1 without
            activation dynamics.
    Activation states (``A`` = ``na``, MuJoCo's ``act``, one per actuator with ``dyntype`` other than none):
        activation_actuator: (A,) its actuator.  activation_kind: (A,) its dyntype, an index into
        ``actuators.ACTIVATION_KINDS``.  activation_dynprm: (A, 3) MuJoCo's ``dynprm[:3]``: a filter's time
        constant [s]; a muscle's activation and deactivation time constants [s] and smoothing width.
        activation_range: (A, 2); activation_limited, activation_early: (A,) bool (``actrange``, ``actlimited``,
        ``actearly``).  activation_kinds: the names of the kinds that occur (static: the step computes no others).
    Muscle gain and bias (MuJoCo ``gaintype``/``biastype`` muscle, ``torchsim.muscles``; ``M`` actuators with a muscle
    gain, ``M'`` with a muscle bias):
        muscle_gain_actuator: (M,) the actuator.  muscle_gain_prm: (M, 9) its ``gainprm[:9]`` with the peak force
        ``gainprm[2]`` resolved [N] (MuJoCo's ``scale / acc0`` where it is negative).  muscle_gain_range: (M, 2) its
        ``actuator_lengthrange`` [m | rad].  muscle_bias_actuator, muscle_bias_prm, muscle_bias_range: the same for
        the muscle biases, from ``biasprm`` (their ``act_bias`` is 0).  act_muscles: whether any (static structure).
    Site transmission (``S`` actuators, MuJoCo ``site`` with an optional ``refsite``, ``torchsim.site_actuators``; a
    missing refsite is the world's origin):
        site_act_actuator: (S,) the actuator.  site_act_body: (2, S) the ext body each site, then each refsite,
        moves with.  site_act_pos: (2, S, 3) each from its body's COM, body frame [m].  site_act_quat: (2, S, 4)
        its orientation in the body frame.  site_act_gear: (S, 6) MuJoCo's 6D ``gear`` (force, torque).
        site_act_has_ref: (S,) bool, whether it has a refsite.  act_on_sites: whether any (static structure).
    Tendons (``T``; a fixed tendon's length is ``L = sum_k coef_k q_k`` [m | rad] over ``K`` joint terms, a spatial
    tendon's the sum of its ``S`` straight segments between sites over their pulley divisors,
    ``torchsim.tendon_paths``):
        ten_wrap_tendon, ten_wrap_dof: (K,) each term's tendon and dof.  ten_wrap_coef: (K,).
        ten_seg_tendon: (S,) each segment's tendon.  ten_seg_body: (2, S) the ext body of each segment's first and
        second site.  ten_seg_pos: (2, S, 3) [m] those sites from their bodies' COMs, body frames (world frame on
        the world).  ten_seg_scale: (S,) 1 / the divisor of the pulley branch holding the segment (1 without).
        ten_is_spatial: (T,) bool, which tendons are spatial.  ten_spatial: whether there are any segments (static
        structure: a model without skips their work).
        ten_stiffness: (T,) [N/m | N m/rad].  ten_damping: (T,) [N s/m].  ten_lengthspring: (T, 2) the spring's
        dead band (no force while ``lo <= L <= hi``).  ten_limited: (T,) bool.  ten_range: (T, 2).
        ten_margin: (T,) [m | rad].  ten_solimp: (T, 5) the limits' MuJoCo ``solimp``.  ten_limit_gains: (T, 2)
        MuJoCo's reference-acceleration gains ``K`` [1/s^2], ``B`` [1/s] from the limits' ``solref``.
        ten_invweight: (T,) [1/kg | 1/(kg m^2)] MuJoCo's tendon inverse inertia at ``qpos0`` (``tendon_invweight0``).
        ten_springs, ten_limits, ten_path_limits, act_on_tendons: whether any tendon has stiffness or damping, any
        fixed tendon a limit, any spatial tendon a limit, any actuator tendon transmission (static structure: a
        model without them skips their work).
        ten_frictionloss: (T,) [N | N m] largest dry-friction force along each tendon (MuJoCo ``frictionloss``; fixed
        tendons over hinges only).  ten_friction: (G,) the tendons with nonzero frictionloss (static structure: a
        model without skips their work; ``joint_space``).  ten_friction_row, ten_friction_dof: (K',) each term of
        those tendons' lengths, its place in ``ten_friction`` and its dof.  ten_friction_coef: (K',).
    Equality constraints (``E`` active MuJoCo ``<equality><tendon>``/``<joint>``, ``torchsim.equality``; each has two
    sides, rows ``e`` and ``E + e``, linear in the dof coordinates over ``K`` terms):
        eq_wrap_side, eq_wrap_dof: (K,) each term's side row and dof.  eq_wrap_coef: (K,).
        eq_ref: (E, 2) the sides at ``qpos0``.  eq_polycoef: (E, 5) MuJoCo's ``polycoef`` (``a1..a4`` zero
        without a second side).  eq_solimp: (E, 5).  eq_gains: (E, 2) ``K`` [1/s^2], ``B`` [1/s] from ``solref``.
        eq_invweight: (E,) MuJoCo's inverse inertia of the constraint at ``qpos0``.
        eq_constraints: whether there are any (static structure: a model without them skips their work).
    Weld and connect constraints (``W`` active MuJoCo ``<equality><weld>``/``<connect>``, ``torchsim.welds``; a
    connect is a weld without rotation rows). Each has two sides, MuJoCo's ``body1``/``site1`` and ``body2``/``site2``:
        weld_frame: (W, 2) the frame each side moves with: an ext body index (the world is ``N``), or ``N + 1 + k``
        for mocap body ``k``.  weld_body: (W, 2) the ext body each side's force acts on (``N`` for the world and
        mocap bodies: none).  weld_anchor: (W, 2, 3) each side's point in its frame, from the frame's origin (a
        moving body's COM) [m].  weld_quat: (W, 2, 4) each side's orientation in its frame (MuJoCo's body or site
        frame; side 1's times ``relpose``).  weld_torquescale: (W,) MuJoCo's ``torquescale``, 0 for a connect.
        weld_solimp: (W, 5).  weld_gains: (W, 2) ``K`` [1/s^2], ``B`` [1/s] from ``solref``.  weld_invweight: (W, 2, 2)
        each side's ``body_invweight0`` (translation [1/kg], rotation [1/(kg m^2)]; 0 for the world and mocap
        bodies), whose sums are MuJoCo's approximate inverse inertia of the rows at ``qpos0``.
        welds: whether there are any (static structure).
    Mocap bodies (``M``, kinematic, MuJoCo's ``mocap_pos``/``mocap_quat``; weld and connect constraints and the contacts
    of their geoms read them, ``torchsim.io_mjcf.bodies``):
        mocap_pos: (M, 3) [m], mocap_quat: (M, 4) each mocap body's frame in the world, batchable: the model pose at
        load; per-env targets are ``sys.replace(mocap_pos=(B, M, 3), mocap_quat=(B, M, 4))``, inputs of the step
        like every per-env parameter (a step kernel takes them as inputs: setting them every step rebuilds nothing;
        a shared ``(M, 3)`` value is built into the kernel, so set targets per env even where they agree).
    Geometry and contacts:
        geom_body: (G,) ext body index (the world's for a mocap body's geom: it takes no impulse).  geom_frame: (G,)
        the frame the geom moves with, indexing the ext bodies followed by the mocap bodies (``N + 1 + k``): its
        body's, or mocap body ``k``'s.  geom_pos, geom_quat: (G, 3), (G, 4) from that frame's origin (a body's COM)
        in that frame (world frame for static geoms).  contact_mocap: whether any contact pair has a mocap body's
        geom (static structure: a model without reads no mocap pose in ``torchsim.collision``).  geom_size: (G, 3)
        MuJoCo sizes.  contact_groups: one per shape pair.
        geom_hull_vert: (G, V, 3) [m] each colliding mesh geom's convex hull vertices, geom frame, padded to the
        model's largest hull (``V`` vertices, 0 without colliding meshes; ``torchsim.io_mjcf.meshes``);
        geom_hull_real: (G, V) false at padding; geom_hull_edge: (G, V, D, 3) [m] the edges from each hull vertex
        to its ``D`` neighbours (padded by repeating the first); geom_hull_plane: (G, F, 4) the hull's face planes
        (outward unit normal, offset [m]), padded by repeating the first.
        hfield_height: (H,) [m] the height fields' grid vertex elevations (MuJoCo's ``hfield_data`` times
        ``hfield_size[2]``, row-major at ``hfield_adr``; one for all envs: a task's terrain is
        ``sys.replace(hfield_height=...)``).  geom_hfield_adr: (G,) a height-field geom's first vertex in it (-1 for
        other geoms).  geom_hfield_grid: (G, 2) its (nrow, ncol).  geom_hfield_size: (G, 4) MuJoCo's ``hfield_size``
        (x, y half extents, elevation scale, base) [m].  hfield_windows: ``(kind, Wy, Wx)`` for each ``*_hfield``
        pair kind, the cells tested around a geom (static; ``torchsim.collision_hfield``).
        contact_soft: whether contacts are MuJoCo's soft constraint (``load_mjcf(contact_model="soft")``, the
        spring method; static).  contact_articulated: whether they are, with the joints, limits and armature,
        solved through the articulation (``contact_model="articulated"``, ``torchsim.tree_solve``; static).
        Per contact point ``C`` (the order of ``collision.contacts``):
        contact_gains: (C, 2) ``K`` [1/s^2], ``B`` [1/s] from the pair's ``solref``.  contact_solimp: (C, 5).
        contact_invweight: (C,) MuJoCo's approximate inverse mass of the contact normal at ``qpos0`` (its two
        bodies' translational ``body_invweight0``) [1/kg].  contact_solimp_square: every contact's ``solimp``
        power is 2 (static).  contact_pyramidal: MuJoCo's friction cone is pyramidal (its default; static).
        contact_inc_point, contact_inc_body, contact_inc_sign: (P,) the (point, moving
        body) incidences, grouped by body, sign +1 where the normal pushes the body; contact_inc_pairs: (Q, 2) the
        ordered pairs of incidences on a common body (the soft contacts' coupling, ``torchsim.soft_contacts``);
        empty unless ``contact_soft``.
    Fluid (MuJoCo's inertia-box model, ``torchsim.fluid``; ``E`` elements, one per moving MuJoCo body with mass):
        fluid: whether the model has a fluid (``density`` or ``viscosity`` > 0; static structure: without it the
        step does no fluid work).  fluid_body: (E,) the ext body carrying each element.
        fluid_pos: (E, 3) the element's centre (its MuJoCo body's COM) from the body COM, body frame [m].
        fluid_rot: (E, 3, 3) the element's box axes (columns: its MuJoCo body's principal axes), body frame.
        fluid_damping: (E, 6) viscous coefficients on the box-frame (angular, linear) velocity [N m s, N s/m].
        fluid_drag: (E, 6) quadratic drag coefficients on the same [N m s^2, N s^2/m^2].  fluid_wind: (3,) [m/s].
    Sensors (MuJoCo's ``<sensor>``, in its ``sensordata`` layout; ``torchsim.sensors`` reads them, never the step):
        nsensordata: MuJoCo's ``nsensordata``.  sensor_names, sensor_kinds: each sensor's name (``#i`` if unnamed)
        and type (MJCF name, e.g. ``"gyro"``).  sensor_adr, sensor_dims: its address and width in ``sensordata``
        (ints).  sensor_skipped: why each is not computed, ``""`` where it is.  sensor_groups: one
        :class:`SensorGroup` per computed type.  sensor_frame_body: (F,) ext body of each frame sensors read;
        sensor_frame_pos: (F, 3) its origin from the body COM, body frame [m]; sensor_frame_quat: (F, 4) its
        orientation in the body frame; frame 0 is the world.  Subtrees as ``K`` terms, one per MuJoCo body with
        mass in the subtree: sensor_subtree_row, sensor_subtree_frame (K,) (the body's inertial frame: its COM and
        principal axes), sensor_subtree_mass (K,) [kg], sensor_subtree_inertia (K, 3) principal moments [kg m^2].
        sensor_magnetic: (3,) MuJoCo's ``magnetic`` field, world frame.  sensor_cutoff: (nsensordata,) MuJoCo's
        ``cutoff`` clamping each real-valued slot to ``[-cutoff, cutoff]`` (inf where none).
        sensor_static_potential: () [J] the gravitational potential energy of the bodies fused into the world.
        Touch zones, one per touch sensor (its group's ``ref``): sensor_touch_size (T, 3) the site's MuJoCo size
        [m], sensor_touch_shape (T,) its shape's code in ``torchsim.render.raycast.CODE``.  sensor_subtree_contact:
        (R, N + 1) 1 where the contact forces on a torchsim body (``N``: the world) push on a subtree row, else 0
        (force and torque sensors subtract them from the subtree's inertial wrench).
    MuJoCo bodies (for poses of fused bodies, e.g. rendering): mjbody_body (nbody,) ext index;
        mjbody_pos, mjbody_quat: frame offset of each MuJoCo body in its fused body's frame.
    The kinematic tree (``torchsim.articulation``; ``C`` columns: the hinge and slide dofs, 3 per ball joint, 6 per
        free body), empty (no columns) unless ``contact_articulated`` or :func:`torchsim.articulation.with_tree`:
        tree_moves: (C, N) 1 where a column moves a body, else 0.  tree_lin, tree_ang: (3, C) the ball joints' and
        free bodies' unit columns (zero for hinges and slides).
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
    jnt_anchor_offset: torch.Tensor
    jnt_general: torch.Tensor
    jnt_anchor_steps: torch.Tensor
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
    jnt_has_offsets: bool
    jnt_has_general: bool
    # dofs
    dof_flat: torch.Tensor
    dof_is_hinge: torch.Tensor
    dof_qpos: torch.Tensor
    dof_qvel: torch.Tensor
    dof_limited: torch.Tensor
    dof_range: torch.Tensor
    dof_limit_gains: torch.Tensor
    dof_solimp: torch.Tensor
    dof_margin: torch.Tensor
    dof_invweight: torch.Tensor
    dof_limits: bool
    dof_solimp_square: bool
    dof_damping: torch.Tensor
    dof_armature: torch.Tensor
    dof_stiffness: torch.Tensor
    dof_springref: torch.Tensor
    dof_ref: torch.Tensor
    dof_frictionloss: torch.Tensor
    dof_friction_hinges: torch.Tensor
    dof_friction_slides: bool
    ball_joint: torch.Tensor
    ball_qpos: torch.Tensor
    ball_qvel: torch.Tensor
    free_body: torch.Tensor
    free_qpos: torch.Tensor
    free_qvel: torch.Tensor
    ball_damping: torch.Tensor
    ball_armature: torch.Tensor
    ball_stiffness: torch.Tensor
    ball_spring: torch.Tensor
    free_damping: torch.Tensor
    free_armature: torch.Tensor
    free_origin: torch.Tensor
    root_passive: bool
    # actuators
    act_dof: torch.Tensor
    act_gear: torch.Tensor
    act_gain: torch.Tensor
    act_bias: torch.Tensor
    act_ctrl_range: torch.Tensor
    act_ctrl_limited: torch.Tensor
    act_force_range: torch.Tensor
    act_force_limited: torch.Tensor
    act_tendon: torch.Tensor
    act_adr: torch.Tensor
    # activation states
    activation_actuator: torch.Tensor
    activation_kind: torch.Tensor
    activation_dynprm: torch.Tensor
    activation_range: torch.Tensor
    activation_limited: torch.Tensor
    activation_early: torch.Tensor
    activation_kinds: tuple
    # muscles
    muscle_gain_actuator: torch.Tensor
    muscle_gain_prm: torch.Tensor
    muscle_gain_range: torch.Tensor
    muscle_bias_actuator: torch.Tensor
    muscle_bias_prm: torch.Tensor
    muscle_bias_range: torch.Tensor
    act_muscles: bool
    # site transmission
    site_act_actuator: torch.Tensor
    site_act_body: torch.Tensor
    site_act_pos: torch.Tensor
    site_act_quat: torch.Tensor
    site_act_gear: torch.Tensor
    site_act_has_ref: torch.Tensor
    act_on_sites: bool
    # tendons
    ten_wrap_tendon: torch.Tensor
    ten_wrap_dof: torch.Tensor
    ten_wrap_coef: torch.Tensor
    ten_seg_tendon: torch.Tensor
    ten_seg_body: torch.Tensor
    ten_seg_pos: torch.Tensor
    ten_seg_scale: torch.Tensor
    ten_is_spatial: torch.Tensor
    ten_spatial: bool
    ten_stiffness: torch.Tensor
    ten_damping: torch.Tensor
    ten_lengthspring: torch.Tensor
    ten_limited: torch.Tensor
    ten_range: torch.Tensor
    ten_margin: torch.Tensor
    ten_solimp: torch.Tensor
    ten_limit_gains: torch.Tensor
    ten_invweight: torch.Tensor
    ten_springs: bool
    ten_limits: bool
    ten_path_limits: bool
    act_on_tendons: bool
    ten_frictionloss: torch.Tensor
    ten_friction: torch.Tensor
    ten_friction_row: torch.Tensor
    ten_friction_dof: torch.Tensor
    ten_friction_coef: torch.Tensor
    # equality constraints
    eq_wrap_side: torch.Tensor
    eq_wrap_dof: torch.Tensor
    eq_wrap_coef: torch.Tensor
    eq_ref: torch.Tensor
    eq_polycoef: torch.Tensor
    eq_solimp: torch.Tensor
    eq_gains: torch.Tensor
    eq_invweight: torch.Tensor
    eq_constraints: bool
    # weld and connect constraints, mocap bodies
    weld_frame: torch.Tensor
    weld_body: torch.Tensor
    weld_anchor: torch.Tensor
    weld_quat: torch.Tensor
    weld_torquescale: torch.Tensor
    weld_solimp: torch.Tensor
    weld_gains: torch.Tensor
    weld_invweight: torch.Tensor
    welds: bool
    mocap_pos: torch.Tensor
    mocap_quat: torch.Tensor
    # geometry
    geom_body: torch.Tensor
    geom_frame: torch.Tensor
    geom_pos: torch.Tensor
    geom_quat: torch.Tensor
    geom_size: torch.Tensor
    geom_hull_vert: torch.Tensor
    geom_hull_real: torch.Tensor
    geom_hull_edge: torch.Tensor
    geom_hull_plane: torch.Tensor
    hfield_height: torch.Tensor
    geom_hfield_adr: torch.Tensor
    geom_hfield_grid: torch.Tensor
    geom_hfield_size: torch.Tensor
    hfield_windows: tuple
    contact_groups: tuple
    contact_soft: bool
    contact_articulated: bool
    contact_mocap: bool
    contact_gains: torch.Tensor
    contact_solimp: torch.Tensor
    contact_invweight: torch.Tensor
    contact_solimp_square: bool
    contact_pyramidal: bool
    contact_inc_point: torch.Tensor
    contact_inc_body: torch.Tensor
    contact_inc_sign: torch.Tensor
    contact_inc_pairs: torch.Tensor
    # fluid
    fluid: bool
    fluid_body: torch.Tensor
    fluid_pos: torch.Tensor
    fluid_rot: torch.Tensor
    fluid_damping: torch.Tensor
    fluid_drag: torch.Tensor
    fluid_wind: torch.Tensor
    # sensors
    nsensordata: int
    sensor_names: tuple
    sensor_kinds: tuple
    sensor_adr: tuple
    sensor_dims: tuple
    sensor_skipped: tuple
    sensor_groups: tuple
    sensor_frame_body: torch.Tensor
    sensor_frame_pos: torch.Tensor
    sensor_frame_quat: torch.Tensor
    sensor_subtree_row: torch.Tensor
    sensor_subtree_frame: torch.Tensor
    sensor_subtree_mass: torch.Tensor
    sensor_subtree_inertia: torch.Tensor
    sensor_magnetic: torch.Tensor
    sensor_cutoff: torch.Tensor
    sensor_static_potential: torch.Tensor
    sensor_touch_size: torch.Tensor
    sensor_touch_shape: torch.Tensor
    sensor_subtree_contact: torch.Tensor
    # MuJoCo body frames
    mjbody_body: torch.Tensor
    mjbody_pos: torch.Tensor
    mjbody_quat: torch.Tensor
    # the kinematic tree (torchsim.articulation)
    tree_moves: torch.Tensor
    tree_lin: torch.Tensor
    tree_ang: torch.Tensor

    @property
    def substep_timestep(self) -> float:
        """The length of one substep [s]: ``timestep / substeps``."""
        return self.timestep / self.substeps

    @property
    def na(self) -> int:
        """Activation states per env (MuJoCo's ``na``; ``State.act``'s width)."""
        return self.activation_actuator.shape[0]

    @property
    def num_bodies(self) -> int:
        return self.body_ipos.shape[0]

    @property
    def num_contacts(self) -> int:
        """Contact points evaluated per env and substep (a box-plane pair counts its 8 corners)."""
        return sum(points_per_pair(g.kind, self.geom_hull_vert.shape[1]) * g.geom_a.shape[0]
                   for g in self.contact_groups)

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
            if isinstance(x, tuple):  # a named tuple (ContactGroup, SensorGroup) keeps its type
                moved = (move(t) for t in x)
                return type(x)(*moved) if hasattr(x, "_fields") else tuple(moved)
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
