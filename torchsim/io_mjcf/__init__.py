"""MJCF -> :class:`System`, through ``mujoco.MjModel`` (MuJoCo compiles masses, inertias and frames for us).

Supported subset (anything else raises ``UnsupportedMJCFError`` naming the element, or warns where ignoring it
is harmless):
- bodies: any tree; bodies without joints are fused into their parent (mass, COM and inertia combined).
- joints per body: one ``free`` (top-level bodies), one ``ball`` (no limit), or up to 3 ``slide`` followed by up
  to 3 ``hinge``. Without slides the hinges may have any anchors (``pos``) and any axes, not parallel (for 3 not in
  one plane) (``torchsim.hinge_anchors``); after slides they share one anchor on orthogonal axes.
  ``range``, ``damping``, ``armature``, ``stiffness``/``springref`` and ``ref`` on hinges and slides.
  ``frictionloss`` on hinges and slides (not on free or ball joints) and on fixed tendons over hinges. ``damping``
  and ``armature`` on free joints (armature only where the body's origin is its centre of mass), ``damping``,
  ``armature`` and ``stiffness`` on ball joints (``joint_space``); not ``stiffness`` on a free joint.
- hinge angles run on through full turns in ``q`` (MuJoCo's ``qpos``), and limits, springs, tendons, equalities
  and servos see them so (also ranges wider than a turn) while a hinge turns less than half a turn per step
  (``kinematics.dof_angles``).
- actuators: joint or site transmission (``site``, ``refsite``), ``gaintype="fixed"|"muscle"``,
  ``biastype="none"|"affine"|"muscle"`` (covers ``motor``, ``position``, ``velocity`` and ``muscle``), activation
  dynamics ``integrator``, ``filter``, ``filterexact`` and ``muscle`` (``State.act``), with ``gear``, ``ctrlrange``,
  ``forcerange``, ``actrange`` and ``actearly``; body transmission (``adhesion``) is refused.
- tendons: ``<fixed>`` over hinges and slides and ``<spatial>`` through sites and pulleys, with ``stiffness``,
  ``springlength``, ``damping``, ``limited``/``range`` (soft, ``solreflimit``/``solimplimit``), and actuators with
  tendon transmission.
- equality constraints: ``<tendon>`` (fixed tendons) and ``<joint>`` (hinges, slides) with ``polycoef``, ``solref``,
  ``solimp``, as soft constraint forces on the dofs (``torchsim.equality``); ``<weld>`` and ``<connect>`` between
  bodies or sites (either may be the world or a mocap body) with ``solref``, ``solimp``, ``anchor``, ``relpose`` and
  ``torquescale``, as soft constraint forces on the bodies (``torchsim.welds``); inactive ones do nothing; flex
  constraints are refused.
- mocap bodies: kinematic, posed per env by ``System.mocap_pos``/``mocap_quat`` (MuJoCo's ``mocap_pos``/
  ``mocap_quat``; ``sys.replace(mocap_pos=(B, M, 3))``), which the welds and connects read. Their geoms move with
  them and collide with moving bodies as static geoms do (at rest, as in MuJoCo); bodies attached to them by joints
  are refused (``torchsim.io_mjcf.bodies``).
- ``<skin>`` is ignored with a warning (it has no physics).
- contact geoms: ``plane`` (static), ``sphere``, ``capsule``, ``box``, ``ellipsoid``, ``cylinder`` (every pair of
  these; ellipsoids and cylinders in ``torchsim.collision_round``); pairs from ``contype``/``conaffinity``,
  ``<exclude>``, ``<contact><pair>`` and MuJoCo's parent filter. Geoms of other types that can never touch
  anything (``contype``/``conaffinity`` filtered out) only contribute mass and are accepted with a warning.
- mesh geoms collide as the convex hull MuJoCo compiles for them (``torchsim.io_mjcf.meshes``), with planes,
  spheres, capsules, ellipsoids, cylinders, boxes and meshes (``torchsim.collision_mesh``); a hull of more than 64
  vertices is refused by name, unless ``load_mjcf(max_hull_vertices=N)`` caps it (MuJoCo's ``maxhullvert``,
  ``torchsim.io_mjcf.hull_caps``; :func:`mujoco_model` gives the capped MuJoCo model).
- height fields (``<hfield>``): static (on the world body), against spheres, capsules, boxes, ellipsoids and
  cylinders, on MuJoCo's triangulated surface in a fixed window of cells around each geom
  (``torchsim.collision_hfield``; meshes against them are refused); the step kernel refuses them (``loop`` runs them).
- fluid: ``<option density viscosity wind>`` with MuJoCo's inertia-box model (``torchsim.fluid``); geoms with
  ``fluidshape="ellipsoid"`` are refused.
- sensors: read from the State by ``torchsim.sensor``/``sensordata`` in MuJoCo's ``sensordata`` layout
  (``torchsim.io_mjcf.sensors`` lists the types computed; the others load with one warning and raise when read).

One module per part of the model: ``subset`` (the checks), ``bodies``, ``joints``, ``actuators``, ``geoms``,
``tendons``, ``equality``, ``fluid``, ``sensors``, ``hull_caps``, ``hfields``; ``spring_stability`` (the spring
method's joint gains against their stability limit).
"""

import numbers
import os
import warnings

import mujoco
import numpy as np
import torch

from torchsim import articulation
from torchsim.io_mjcf.actuators import actuator_fields
from torchsim.io_mjcf.bodies import fuse_bodies
from torchsim.io_mjcf.equality import equality_fields, weld_fields
from torchsim.io_mjcf.fluid import fluid_fields
from torchsim.io_mjcf.geoms import geom_fields
from torchsim.io_mjcf.hull_caps import capped_model
from torchsim.io_mjcf.joints import joint_fields
from torchsim.io_mjcf.sensors import sensor_fields
from torchsim.io_mjcf import spring_stability
from torchsim.io_mjcf.subset import UnsupportedMJCFError, check_supported
from torchsim.io_mjcf.tendons import tendon_fields
from torchsim.methods import METHODS
from torchsim.system import System

__all__ = ["JOINT_DAMPING", "JOINT_STIFFNESS", "UnsupportedMJCFError", "load_mjcf", "mujoco_model"]

JOINT_STIFFNESS, JOINT_DAMPING = 0.2, 0.5  # load_mjcf's defaults (spring method)
CONTACT_MODELS = ("impulse", "soft", "articulated")


def load_mjcf(
    source,
    method: str = "spring",
    substeps: int | None = None,
    dtype: torch.dtype = torch.float32,
    device="cpu",
    joint_stiffness: float | None = None,
    joint_damping: float | None = None,
    contact_timeconst: float = 0.02,
    contact_model: str = "impulse",
    xpbd_iterations: int = 1,
    max_speed: float = 1e3,
    max_distance: float = 1e4,
    max_hull_vertices: int | None = None,
) -> System:
    """Load an MJCF model from a file path or an XML string.

    Args:
        source: path to an ``.xml`` file, or the XML text itself.
        method: ``"xpbd"`` (position-based projection of joints, limits and contacts) or ``"spring"`` (explicit
            stiff springs for joints and limits, velocity impulses for contacts, in the spirit of Brax v1).
        substeps: substeps per ``<option timestep>``, a positive integer; default ``ceil(timestep / h)`` with h = 0.5 ms
            (ant: 20), raised (spring method, with a warning) where a joint would sag more than 3e-5 rad under the
            model's weight (a robot arm fixed to the world, ``torchsim.io_mjcf.spring_stability.stiff_enough``);
            with ``contact_model="articulated"`` 1, MuJoCo's own Euler step (4 where the model asks for RK4, whose
            four evaluations of the dynamics they cost: gymnasium's Ant then follows MuJoCo at 1.4x MuJoCo's own
            timestep sensitivity, 9.8x at 1).
        joint_stiffness: spring method only: fraction of a joint's error its spring removes per substep
            (gain ``stiffness / h^2 K^-1``, ``K`` the joint's inverse-inertia block); default
            ``JOINT_STIFFNESS = 0.2``.
        joint_damping: spring method only: fraction of a joint's error rate its damper removes per substep;
            default ``JOINT_DAMPING = 0.5``. Where the model's stability number ``lam`` makes
            ``lam (stiffness + 2 damping)`` exceed 3.8 (the explicit springs' limit is 4: a light body carrying a
            much heavier child, ``torchsim.io_mjcf.spring_stability``), the ones left to their defaults are lowered
            in proportion to bring it to 3.2, with a warning; values given are kept, with a warning that the
            springs may diverge.
        contact_timeconst: spring method only: MuJoCo's ``solref`` time constant [s] (0.02 s, its default):
            penetration is removed at a separating speed ``depth / (e timeconst)``, the peak speed of MuJoCo's
            critically damped contact pushing out a body that starts that deep (Baumgarte). A per-substep
            fraction instead would launch bodies that start interpenetrating at ``depth / h``. XPBD removes
            penetration in full and zeroes the contacts' normal speed.
        contact_model: spring method only. ``"impulse"`` (default): the Brax-style impulse above, which stops a
            landing body within a substep. ``"soft"``: MuJoCo's soft contact on the normal, with each pair's
            ``solref``, ``solimp`` and ``margin`` (``contact_timeconst`` unused): a body sinks in and is pushed
            back along MuJoCo's spring-damper, and rests as deep as in MuJoCo (``torchsim.soft_contacts``).
            ``"articulated"``: MuJoCo's Euler step on the rigid tree: each substep's velocities solved through the
            articulation's joint-space inertia with its bias forces, armature, damping, soft limits and soft
            contacts with friction on MuJoCo's pyramid in one system, the poses put back onto the joints by forward
            kinematics, so the joints are exact and an impulse on a foot moves the leg and the torso above it
            (``torchsim.tree_solve``; dense in the tree's dofs and the contact points; dry friction on slides and
            ``joint_stiffness``/``joint_damping``, which it has no springs for, refused). Friction is a
            Coulomb-capped impulse in the other two.
        xpbd_iterations: XPBD only: projection passes (contacts, then joint colours) per substep.
        max_speed, max_distance: an env whose body speed [m/s] or distance from the origin [m] exceeds these is
            flagged as diverged.
        max_hull_vertices: cap every colliding mesh's convex hull at this many vertices (4 to 64) with MuJoCo's
            ``maxhullvert`` (one warning names the meshes capped); default: none, and a hull of more than 64
            vertices is refused. The System is built from the capped MuJoCo model, :func:`mujoco_model`'s, which
            is the one to compare against.
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; expected one of {tuple(METHODS)}")
    if contact_model not in CONTACT_MODELS:
        raise ValueError(f"unknown contact_model {contact_model!r}; expected one of {CONTACT_MODELS}")
    if contact_model != "impulse" and method != "spring":
        raise ValueError(f"contact_model={contact_model!r} is implemented for the spring method only, not {method!r}")
    m = mujoco_model(source, max_hull_vertices)
    check_supported(m)
    articulated = contact_model == "articulated"
    if articulated and (joint_stiffness is not None or joint_damping is not None):
        raise ValueError("joint_stiffness and joint_damping size the spring method's joint springs; "
                         "contact_model='articulated' holds its joints exactly and has none")
    free_substeps = substeps is None
    if free_substeps and articulated:  # MuJoCo's Euler step; RK4's four evaluations of the dynamics as 4 substeps
        substeps = 4 if m.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4 else 1
    elif free_substeps:
        substeps = max(1, int(np.ceil(m.opt.timestep / METHODS[method].default_substep_timestep - 1e-9)))
    _check_substeps(substeps)
    fused, fields = fuse_bodies(m)
    joints, jnt_dof = joint_fields(m, fused)
    fields |= joints | actuator_fields(m, jnt_dof, fused) | geom_fields(m, fused, contact_soft=contact_model == "soft")
    fields |= articulation.no_tree(len(fields["body_ipos"]))
    fields |= tendon_fields(m, jnt_dof, fused) | equality_fields(m, jnt_dof) | weld_fields(m, fused)
    fields |= fluid_fields(m, fused)
    fields |= sensor_fields(m, fused, jnt_dof)
    gravity = m.opt.gravity * (0.0 if m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_GRAVITY) else 1.0)
    sys = System(
        nq=m.nq, nv=m.nv, nu=m.nu, timestep=float(m.opt.timestep), substeps=int(substeps), method=method,
        gravity=torch.as_tensor(gravity), q0=torch.as_tensor(m.qpos0.copy()),
        joint_stiffness=JOINT_STIFFNESS if joint_stiffness is None else joint_stiffness,
        joint_damping=JOINT_DAMPING if joint_damping is None else joint_damping, contact_timeconst=contact_timeconst,
        xpbd_iterations=xpbd_iterations, contact_soft=contact_model == "soft",
        contact_articulated=articulated, max_speed=max_speed,
        max_distance=max_distance, **fields,
    )
    if articulated:
        if articulation.refusal(sys):
            raise UnsupportedMJCFError(f"contact_model='articulated': {articulation.refusal(sys)}")
        if sys.dof_friction_slides:
            raise UnsupportedMJCFError("contact_model='articulated': dry friction (frictionloss) on slide joints is "
                                       "not supported; use contact_model='soft'")
        sys = articulation.with_tree(sys)
    if method == "spring" and not articulated:
        sys = _stable_springs(sys, joint_stiffness is None, joint_damping is None)
        sys = spring_stability.stiff_enough(sys, free_substeps)
    return sys.to(device=device, dtype=dtype)


def _stable_springs(sys: System, free_stiffness: bool, free_damping: bool) -> System:
    """``sys`` with its joint springs' ``joint_stiffness``/``joint_damping`` lowered where the stability number
    demands it and the caller left them to their defaults (``free_*``), with a warning (:func:`load_mjcf`)."""
    lam, body = spring_stability.stability_number(sys)
    kappa, zeta = sys.joint_stiffness, sys.joint_damping
    if lam * (kappa + 2.0 * zeta) <= spring_stability.LIMIT:
        return sys
    budget = spring_stability.TARGET / lam  # kappa + 2 zeta to reach
    if free_stiffness and free_damping:
        kappa, zeta = kappa * budget / (kappa + 2.0 * zeta), zeta * budget / (kappa + 2.0 * zeta)
    elif free_damping and budget - kappa > 0.0:
        zeta = (budget - kappa) / 2.0
    elif free_stiffness and budget - 2.0 * zeta > 0.0:
        kappa = budget - 2.0 * zeta
    heavy = ": a body carrying children heavier than itself about its joints" if lam > spring_stability.USUAL else ""
    where = f"stability number {lam:.2f} at qpos0 (its mode mostly moves body {sys.body_names[body]!r}{heavy})"
    if (kappa, zeta) == (sys.joint_stiffness, sys.joint_damping):
        warnings.warn(f"spring method: the explicit joint springs are at or beyond their stability limit, {where}: "
                      f"{lam:.2f} x (joint_stiffness {kappa:g} + 2 x joint_damping {zeta:g}) = "
                      f"{lam * (kappa + 2 * zeta):.2f} (4 or more diverges); joint_stiffness + 2 joint_damping <= "
                      f"{budget:.3g} (or method='xpbd') keeps them stable", stacklevel=3)
        return sys
    warnings.warn(f"spring method: joint_stiffness {sys.joint_stiffness:g} -> {kappa:.3g} and joint_damping "
                  f"{sys.joint_damping:g} -> {zeta:.3g}, {where}: at the defaults the explicit joint springs would "
                  f"be at or beyond their stability limit ({lam:.2f} x (stiffness + 2 damping) = "
                  f"{lam * (sys.joint_stiffness + 2 * sys.joint_damping):.2f}; 4 or more diverges)", stacklevel=3)
    return sys.replace(joint_stiffness=kappa, joint_damping=zeta)


def _check_substeps(substeps) -> None:
    """A substep lasts ``timestep / substeps``: zero would divide by zero, a negative count step back in time, and a
    fraction be truncated to a count the caller did not ask for."""
    if isinstance(substeps, bool) or not isinstance(substeps, numbers.Integral) or substeps < 1:
        raise ValueError(f"substeps must be a positive integer (substeps per <option timestep>), got {substeps!r}")


def mujoco_model(source, max_hull_vertices: int | None = None) -> mujoco.MjModel:
    """The MuJoCo model :func:`load_mjcf` builds its System from, for ``source`` (a path or the XML text) and its
    ``max_hull_vertices`` (``torchsim.io_mjcf.hull_caps``): with a cap, the model whose colliding meshes' hulls
    MuJoCo compiled capped."""
    text = str(source)
    is_xml = text.lstrip().startswith("<")
    if not is_xml and not os.path.isfile(text):
        raise FileNotFoundError(f"MJCF file not found: {text}")
    m = (mujoco.MjModel.from_xml_string if is_xml else mujoco.MjModel.from_xml_path)(text)
    if max_hull_vertices is None:
        return m
    return capped_model(m, lambda: (mujoco.MjSpec.from_string if is_xml else mujoco.MjSpec.from_file)(text),
                        max_hull_vertices)
