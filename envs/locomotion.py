"""Locomotion tasks: run forward along +x without falling (Brax's current definitions of each task).

All of them reward forward progress of the root, measured over the env step ``dt`` from the root's x coordinate
(Humanoid: the whole body's centre of mass), pay a control cost, and (except HalfCheetah) a healthy bonus per step
with termination once the body leaves its healthy range.
"""

import torch

from torchsim import spatial
from torchsim.envs.base import TorchsimEnv
from torchsim.state import State


class _Runner(TorchsimEnv):
    """Shared reward: ``forward_weight * vx + healthy_reward - ctrl_cost_weight * |ctrl|^2``."""

    forward_weight = 1.0
    healthy_reward = 1.0
    ctrl_cost_weight = 1e-3

    def _forward_position(self, state: State) -> torch.Tensor:
        return state.q[:, 0]

    def _reward(self, before: State, after: State, ctrl: torch.Tensor) -> torch.Tensor:
        velocity = (self._forward_position(after) - self._forward_position(before)) / self.dt
        return self.forward_weight * velocity + self.healthy_reward - self.ctrl_cost_weight * (ctrl * ctrl).sum(-1)


class Ant(_Runner):
    """Quadruped (``ant.xml``: 9 bodies, 8 hinges, 4 foot-floor contact pairs), ``dt = 5 x 10 ms``.

    Observation (27): ``q[2:]`` (torso z, torso quaternion wxyz, 8 joint angles), ``qd`` (torso linear and angular
    velocity, 8 joint rates). Action (8): hip and ankle motors (gear 150). Reward:
    ``vx + 1 - 0.5 |a|^2`` (vx: torso x velocity over the step; no contact cost, as Brax's default).
    Terminates when the torso height leaves [0.2, 1.0] m. Reset: ``home`` pose + U(-0.1, 0.1) on q, 0.1 N(0, 1)
    on qd. Random actions often launch the torso above 1 m within tens of steps (MuJoCo on this model too).

    Versus MuJoCo (``studies/check_models.py``, full-range random actions, 0.25 s): torso within 9 cm (MuJoCo at
    10 ms vs 2.5 ms: 4 cm); the torso travels 0.15 m vs MuJoCo's 0.24 m (impulse contacts).
    """

    model_file = "ant.xml"
    frame_skip = 5
    # MuJoCo's soft contact normal: the main job's policy then keeps 0.23 of its return when run in MuJoCo (impulse
    # contacts: 0.017) and reaches 4000 in fewer env steps (docs/physics.md, "Policy transfer")
    contact_model = "soft"
    observation_size = 27
    ctrl_cost_weight = 0.5

    def _observation(self, state, ctrl):
        return torch.cat((state.q[:, 2:], state.qd), -1)

    def _terminated(self, state):
        z = state.q[:, 2]
        return (z < 0.2) | (z > 1.0)


class HalfCheetah(_Runner):
    """Planar cheetah (``halfcheetah.xml``: root x/z slides and pitch hinge, 6 leg hinges), ``dt = 5 x 10 ms``.

    Observation (17): ``q[1:]`` (root z, root pitch, 6 joint angles), ``qd`` (9). Action (6). Reward:
    ``vx - 0.1 |a|^2``; no healthy bonus and no termination (time limit only). Reset: U(-0.1, 0.1) on q,
    0.1 N(0, 1) on qd. Versus MuJoCo (random actions, 0.25 s): root within 1.1 cm (MuJoCo's own 10 ms vs 2.5 ms:
    0.8 cm).
    """

    model_file = "halfcheetah.xml"
    frame_skip = 5
    substeps = 10  # 1 ms: as close to MuJoCo as 0.5 ms over 0.25 s (envs/assets/halfcheetah.xml header)
    observation_size = 17
    healthy_reward = 0.0
    ctrl_cost_weight = 0.1

    def _observation(self, state, ctrl):
        return torch.cat((state.q[:, 1:], state.qd), -1)


class _PlanarWalker(_Runner):
    """Hopper and Walker2d: root x/z slides and pitch hinge at the torso; observation ``q[1:]`` and
    ``clip(qd, -10, 10)``. As in Brax, ``q[1]`` is the torso's height change from its 1.25 m start (rootz has no
    ``ref``) and the health check reads the torso frame's world height."""

    frame_skip = 4
    named_bodies = ("torso",)
    noise_q = ("uniform", 5e-3)
    noise_qd = ("uniform", 5e-3)
    healthy_z = (0.0, float("inf"))
    healthy_angle = (-1.0, 1.0)
    healthy_state = float("inf")

    def _observation(self, state, ctrl):
        return torch.cat((state.q[:, 1:], state.qd.clamp(-10.0, 10.0)), -1)

    def _terminated(self, state):
        z, angle = self.mj_body_positions(state)[:, 0, 2], state.q[:, 2]  # torso frame height [m], pitch [rad]
        rest = torch.cat((state.q[:, 2:], state.qd), -1).abs().amax(-1)
        healthy = ((z > self.healthy_z[0]) & (z < self.healthy_z[1]) & (angle > self.healthy_angle[0])
                   & (angle < self.healthy_angle[1]) & (rest < self.healthy_state))
        return ~healthy


class Hopper(_PlanarWalker):
    """One-legged hopper (``hopper.xml``), ``dt = 4 x 2 ms``.

    Observation (11): ``q[1:]`` (torso height change, torso pitch, thigh/leg/foot angles), ``clip(qd, -10, 10)`` (6).
    Action (3). Reward: ``vx + 1 - 1e-3 |a|^2``. Terminates unless torso height > 0.7 m, |pitch| < 0.2 rad and
    every entry of ``(q[2:], qd)`` is within (-100, 100). Reset: U(-5e-3, 5e-3) on q and qd.
    Physics: MuJoCo's Euler step on the rigid tree (``contact_model="articulated"``, one substep per 2 ms): its
    0.5 s landing stays on MuJoCo's path to 0.2 % of MuJoCo's own timestep sensitivity
    (``tests/test_articulated_contacts.py``), and the tuned PPO recipe's policy keeps 1.03 of its return in MuJoCo
    (impulse contacts: 0.10; docs/physics.md, "Policy transfer").
    """

    model_file = "hopper.xml"
    contact_model = "articulated"
    observation_size = 11
    healthy_z = (0.7, float("inf"))
    healthy_angle = (-0.2, 0.2)
    healthy_state = 100.0


class Walker2d(_PlanarWalker):
    """Planar biped (``walker2d.xml``), ``dt = 4 x 2 ms``.

    Observation (17): ``q[1:]`` (torso height change, pitch, 6 leg angles), ``clip(qd, -10, 10)`` (9). Action (6).
    Reward: ``vx + 1 - 1e-3 |a|^2``. Terminates unless 0.8 < torso height < 2.0 m and |pitch| < 1 rad.
    Reset: U(-5e-3, 5e-3) on q and qd. Versus MuJoCo (random actions, 0.25 s): root within 9.4 cm; even with
    zero actions the torso drifts 1.3 cm and pitches 0.01 rad on landing where MuJoCo lands straight (contact
    model; not resolved).
    """

    model_file = "walker2d.xml"
    observation_size = 17
    healthy_z = (0.8, 2.0)


class Humanoid(_Runner):
    """3-D biped (``humanoid.xml``: 11 bodies, 17 hinge dofs, feet and shins collide with the floor),
    ``dt = 5 x 3 ms``.

    Observation (244): ``q[2:]`` (22), ``qd`` (23), per body (11) its centre-of-mass-based inertia (10: inertia
    xx yy zz xy xz yz about the whole body's centre of mass, mass times COM offset, mass; world axes) and
    velocity (6: angular, then linear velocity of the point at the whole body's COM moving with the body), and
    the actuators' generalized forces ``qfrc_actuator`` (23; zero on the free joint). Action (17) in [-1, 1]
    mapped to ctrlrange [-0.4, 0.4] (gear 100-350). Reward: ``1.25 vx_com + 5 - 0.1 |ctrl|^2`` (vx_com: whole-body
    COM velocity over the step). Terminates when the torso height leaves [1.0, 2.0] m. Reset: U(-0.01, 0.01) on
    q and qd. Versus MuJoCo (random actions, 0.25 s): torso within 1.9 cm (MuJoCo 3 ms vs 0.75 ms: 0.6 cm).
    """

    model_file = "humanoid.xml"
    frame_skip = 5
    # MuJoCo's soft contact normal: a policy trained 15 minutes (3.2M env steps, one seed) then scores 1.27 times its
    # torchsim return in MuJoCo and climbed faster (6230 at 3.0M env steps; impulse contacts: 0.92 and 1830;
    # docs/physics.md, "Policy transfer")
    contact_model = "soft"
    observation_size = 244
    forward_weight = 1.25
    healthy_reward = 5.0
    ctrl_cost_weight = 0.1
    noise_q = ("uniform", 1e-2)
    noise_qd = ("uniform", 1e-2)

    def _com(self, state: State) -> torch.Tensor:
        mass = self.sys.body_mass.expand(state.x_pos.shape[:2])
        return (mass[..., None] * state.x_pos).sum(1) / mass.sum(-1, keepdim=True)

    def _forward_position(self, state):
        return self._com(state)[:, 0]

    def _terminated(self, state):
        z = state.q[:, 2]
        return (z < 1.0) | (z > 2.0)

    def _actuator_forces(self, state: State, ctrl: torch.Tensor) -> torch.Tensor:
        """MuJoCo's ``qfrc_actuator`` of motors: gear times gain times control on each actuated dof."""
        sys = self.sys
        return torch.zeros_like(state.qd).index_add(1, sys.dof_qvel[sys.act_dof], sys.act_gain * ctrl * sys.act_gear)

    def _observation(self, state, ctrl):
        sys = self.sys
        mass = sys.body_mass.expand(state.x_pos.shape[:2])[..., None]
        offset = state.x_pos - self._com(state)[:, None]
        rot = spatial.batch_first.quat_to_mat(state.x_quat)
        inertia = rot @ sys.body_inertia @ rot.transpose(-1, -2)
        eye = torch.eye(3, dtype=offset.dtype, device=offset.device)
        inertia = inertia + mass[..., None] * ((offset * offset).sum(-1)[..., None, None] * eye
                                               - offset[..., :, None] * offset[..., None, :])
        upper = inertia[..., [0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]]
        com_inertia = torch.cat((upper, mass * offset, mass), -1)
        com_velocity = torch.cat((state.xd_ang, state.xd_vel - spatial.batch_first.cross(state.xd_ang, offset)), -1)
        return torch.cat((state.q[:, 2:], state.qd, com_inertia.flatten(1), com_velocity.flatten(1),
                          self._actuator_forces(state, ctrl)), -1)
