"""UR5e reach: bring the UR5e's tool frame to a random reachable target; the arm comes in through URDF."""

import math
import xml.etree.ElementTree as ET

import torch

import torchsim
from torchsim.envs.base import TorchsimEnv

#: Joint servo gains: stiffness [N m/rad] as MuJoCo Menagerie's UR5e (size-3 joints, then size-1 wrists) and
#: damping [N m s/rad] half of Menagerie's (see ``UR5eReach``).
SERVO_KP = (2000.0, 2000.0, 2000.0, 500.0, 500.0, 500.0)
SERVO_KD = (200.0, 200.0, 200.0, 40.0, 40.0, 40.0)
HOME = (-math.pi / 2, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0)
SHOULDER, SHOULDER_INERTIA_SCALE = "shoulder_link", 10.0
LINKS = ("shoulder_link", "upper_arm_link", "forearm_link", "wrist_1_link", "wrist_2_link", "wrist_3_link")


def servo_model(mjcf: str, kp, kd, home) -> str:
    """The MJCF translated from the UR5e URDF, made a position-controlled arm: each joint motor becomes a
    ``position`` servo (force ``kp (target - q)`` clipped to the URDF effort), the servo damping is joint damping
    ``kd`` (implicit in MuJoCo's Euler and in torchsim's joint-space solve, so it stays stable at the light wrists),
    contacts are off (the task has no obstacles), a floor and a light are added for videos (visual only) and
    ``home`` is the first keyframe.

    The shoulder link's inertia about its two horizontal axes is raised tenfold. Its only joint, the pan, turns it
    about the world-fixed vertical, so those two moments never enter the true dynamics (MuJoCo's trajectories are
    identical to rounding); but torchsim's spring joints are stiff in proportion to the inertia they hold, and the
    light shoulder link (0.01 kg m^2) is what the pan joint holds upright against up to 150 N m of lift torque.
    """
    root = ET.fromstring(mjcf)
    shoulder = next(b for b in root.iter("body") if b.get("name") == SHOULDER).find("inertial")
    ixx, iyy, *rest = map(float, shoulder.get("fullinertia").split())
    raised = (SHOULDER_INERTIA_SCALE * ixx, SHOULDER_INERTIA_SCALE * iyy, *rest)
    shoulder.set("fullinertia", " ".join(map(repr, raised)))
    ET.SubElement(root.find("option"), "flag", contact="disable")
    joints = {j.get("name"): j for j in root.iter("joint")}
    actuators = root.find("actuator")
    motors = list(actuators)
    if len(motors) != len(kp):
        raise ValueError(f"expected {len(kp)} joint motors, found {len(motors)}")
    for motor, gain, damping in zip(motors, kp, kd):
        effort = float(motor.get("ctrlrange").split()[1])
        actuators.remove(motor)
        joints[motor.get("joint")].set("damping", repr(damping))
        ET.SubElement(actuators, "position", name=motor.get("name"), joint=motor.get("joint"), kp=repr(gain),
                      forcerange=f"{-effort!r} {effort!r}")
    world = root.find("worldbody")
    world.insert(0, ET.Element("geom", name="floor", type="plane", size="3 3 0.1", rgba="0.8 0.9 0.8 1"))
    world.insert(0, ET.Element("light", pos="0 0 3", dir="0 0 -1", directional="true"))
    ET.SubElement(ET.SubElement(root, "keyframe"), "key", name="home", qpos=" ".join(map(repr, home)))
    return ET.tostring(root, encoding="unicode")


class UR5eReach(TorchsimEnv):
    """UR5e arm (``ur5e.urdf`` through ``urdf_to_mjcf``, armature 0.1 as Menagerie; fixed base, gravity, no
    contacts) moving its tool frame ``tool0`` to a target drawn per episode; ``dt = 20 x 2 ms``.

    Actions (6) are joint-space PD targets, not torques. Torque control has to hold ~60 N m of gravity on the
    shoulder before it can move at all, so random torques mostly fling or drop the arm and the policy must learn
    the arm's dynamics; a position servo turns the task into kinematics (where should the joints go). Each step
    the servo target is ``q - G(q) / kp + (effort / kp) a``: the measured angles, a gravity-compensation offset
    (``G``: the generalized gravity force at the current pose, from the links' masses and positions, as a real UR
    controller compensates gravity) and the action scaled so that ``|a| = 1`` asks for the joint's full effort
    (150 N m, wrists 28 N m). So ``a = 0`` holds the arm still and ``a`` acts as a joint-velocity command, up to
    ``effort / kd`` = 0.75 rad/s (wrists 0.7 rad/s; ~0.5 rad/s measured at ``a = 1``, the target being re-based
    once per step). Servo stiffness is Menagerie's; its damping (400/100) is halved, since with the force clipped
    to the effort the damping caps the speed (Menagerie's: 0.38 rad/s).

    Observation (30): cos and sin of the 6 joint angles, the 6 joint rates, the tool position, the target, target
    minus tool (world frame, metres), and target minus tool again in units of 5 cm, clipped to [-1, 1]. That last
    feature is what lets PPO close the final centimetres: after running normalisation the metre-scale error's 2 cm
    is ~0.05 of its spread, the clipped one's 2 cm is ~0.4 (without it the reach stalled at ~10 cm; with it 36% of
    evaluation episodes ended within 2 cm after 0.5M steps, against 0%: docs/training_robots.md). Reward: ``-|tool - target| - 0.01 |a|^2 + 1[|tool - target| < 0.02]``
    (the design in ``shared/reference/ur5e.md`` section 4; Brax v1 rewarded progress plus hits). Success: the
    tool ends the episode within 2 cm of the target (``goal_distance``). No termination. Reset: ``HOME`` +
    U(-0.1, 0.1) rad, rates 0.1 N(0, 1); the target stays fixed for the episode (``task``), drawn from a pool of
    ``tool0`` positions at uniformly random joint angles within the URDF limits, kept if ``z >= 0.05`` m and at
    least 0.2 m from the base axis: reachable by construction. The joints' limits (+-2 pi, the elbow's +-pi) hold as
    in MuJoCo (a substep reads each angle continuously, ``kinematics.dof_angles``); there is no self-collision.

    Physics: the spring method at 1 ms substeps (2 per 2 ms timestep). XPBD is not used: on this arm it lags MuJoCo
    (a 0.4 s passive fall differs by 0.12 rad at 0.5 ms substeps; under the servos the shoulder barely turns while
    MuJoCo's turns 0.1 rad in 0.2 s). Versus MuJoCo on the same MJCF and control law (float64, 4 arms, 3 s: random
    actions held 0.4 s for 1.5 s, then ``a = 0``): tool within 2.5 cm. torchsim's joints give under load (anchors
    1.9 mm, axes 0.027 rad, mostly the shoulder lift under 150 N m), so the tool sits up to 2.6 cm from the forward
    kinematics of the measured angles while moving, ~4 mm at rest. At 0.5 ms substeps (``substeps=4``, twice the
    cost): 0.7 cm from MuJoCo, 0.8 cm from FK. Reward and success read the simulated tool, so the policy closes the
    loop on where the tool really is.
    """

    model_file = "ur5e.urdf"
    urdf_armature = 0.1
    frame_skip = 20
    substeps = 2
    observation_size = 30
    task_size = 3
    success_distance = 0.02
    fine_error_scale = 0.05  # [m]
    named_bodies = LINKS + ("tool0",)
    target_pool_size = 1 << 14  # candidate joint configurations; 47% pass the workspace filter
    min_target_height = 0.05  # [m]
    min_target_radius = 0.2  # [m] from the base's z axis
    ctrl_cost_weight = 0.01
    hit_bonus = 1.0

    def _model_xml(self):
        return servo_model(super()._model_xml(), SERVO_KP, SERVO_KD, HOME)

    def _setup(self):
        sys = self.sys
        if (sys.act_dof.tolist(), sys.jnt_child.tolist(), sys.body_parent.tolist()) != (
                list(range(6)), list(range(6)), [6, 0, 1, 2, 3, 4]):
            raise RuntimeError("UR5eReach expects a serial chain of 6 links, one hinge and one actuator each, in order")
        self.kp = torch.tensor(SERVO_KP, dtype=sys.dtype, device=self.device)
        self.max_offset = sys.act_force_range[:, 1] / self.kp  # [rad] target offset of |a| = 1: full effort
        # carried[j, n]: joint j carries body n (its child link or one further out along the chain)
        self.carried = torch.ones(6, 6, dtype=sys.dtype, device=self.device).triu()
        self.target_q, self.targets = self._target_pool()

    def _target_pool(self):
        """Joint angles ``(K, 6)`` and the tool positions ``(K, 3)`` they put it at, for the ``K`` of
        ``target_pool_size`` uniform draws within the joint limits that pass the workspace filter (a fixed seed:
        every env draws from the same pool, independent of the global RNG)."""
        sys = self.sys
        low, high = sys.dof_range.unbind(-1)
        draw = torch.rand(self.target_pool_size, 6, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
        q = (low.cpu().double() + (high - low).cpu().double() * draw).to(sys.dtype).to(self.device)
        state = torchsim.init(sys, q, torch.zeros_like(q))
        tool = self.mj_body_positions(state)[:, -1]
        keep = (tool[:, 2] >= self.min_target_height) & (tool[:, :2].norm(dim=-1) >= self.min_target_radius)
        return q[keep], tool[keep]

    def _sample_task(self, state):
        index = torch.randint(self.targets.shape[0], (state.q.shape[0],), device=self.device)
        return self.targets[index]

    def _gravity_force(self, state):
        """Generalized gravity force ``(B, 6)`` [N m] on each joint: the moment of the weights of the links it
        carries about its anchor, along its axis (every UR joint turns about its child link's z axis, at its
        origin)."""
        pos, quat = self.mj_body_poses(state)
        anchor, axis = pos[:, :6, None], torchsim.spatial.batch_first.quat_rotate(quat[:, :6], pos.new_tensor([0.0, 0.0, 1.0]))
        weight = (self.sys.body_mass[..., None] * self.sys.gravity).unsqueeze(-3)  # (..., 1, N, 3) [N]
        moment = torchsim.spatial.batch_first.cross(state.x_pos[:, None] - anchor, weight)  # (B, 6, N, 3) about each anchor
        return ((moment * axis[:, :, None]).sum(-1) * self.carried).sum(-1)

    def _hold_target(self, state):
        """Servo targets ``(B, 6)`` that hold the arm still in ``state``: the angles plus the gravity offset."""
        return state.q - self._gravity_force(state) / self.kp

    def _ctrl(self, action):
        return self._hold_target(self.state) + self.max_offset * action.clamp(-1.0, 1.0)

    def _tool(self, state):
        return self.mj_body_positions(state)[:, -1]

    def _observation(self, state, ctrl):
        tool = self._tool(state)
        error = self.task - tool
        fine_error = (error / self.fine_error_scale).clamp(-1.0, 1.0)
        return torch.cat((torch.cos(state.q), torch.sin(state.q), state.qd, tool, self.task, error, fine_error), -1)

    def _goal_distance(self, state):
        return (self.task - self._tool(state)).norm(dim=-1)

    def _reward(self, before, after, ctrl):
        action = (ctrl - self._hold_target(before)) / self.max_offset
        distance = self._goal_distance(after)
        return (-distance - self.ctrl_cost_weight * (action * action).sum(-1)
                + self.hit_bonus * (distance < self.success_distance).to(distance.dtype))
