"""Arm tasks: bring the fingertip to a target (Reacher), push an object onto a goal (Pusher); Brax's definitions."""

import torch

from torchsim.envs.base import TorchsimEnv, ring_points


class Reacher(TorchsimEnv):
    """Two-link planar arm (``reacher.xml``; the target is a body on two slide joints), ``dt = 2 x 10 ms``.

    Observation (11): cos and sin of the 2 arm angles, target x/y (``q[2:4]``), the 2 arm rates, fingertip minus
    target (3). Action (2): shoulder and elbow motors. Reward: ``-|fingertip - target| - |a|^2``. No termination.
    Success: the fingertip ends the episode within 2 cm of the target (``goal_distance`` is emitted every step).
    Reset: arm angles U(-0.1, 0.1) about zero and rates U(-0.005, 0.005); the target at radius 0.2 U(0, 1) and a
    uniform random angle, at rest. The model's links are 10x denser than the standard file's (the spring method
    diverges with the standard 1-kg-m^2 armature on links 7700x lighter); in MuJoCo that changes the arm's motion
    by 0.003 rad over 1 s of small random actions. Versus MuJoCo on this model (1 s, actions at 0.1x range):
    joints within 0.012 rad (MuJoCo's own 10 ms vs 2.5 ms: 0.010 rad).
    """

    model_file = "reacher.xml"
    frame_skip = 2
    # 30 substeps (0.33 ms): at 20 a shoulder spun up to 45 rad/s by random actions can whirl its arm out of the
    # plane, the joint springs' held gains too slow for the spin (1 of 4096 envs in the soak, docs/stability.md)
    substeps = 30
    observation_size = 11

    named_bodies = ("fingertip", "target")
    success_distance = 0.02

    def _sample_init(self, n):
        q = self.init_q.expand(n, -1) + self._noise(("uniform", 0.1), (n, self.sys.nq))
        q = torch.cat((q[:, :2], ring_points(q.new_zeros(n, 2), 0.0, 0.2)), -1)
        qd = torch.cat((self._noise(("uniform", 5e-3), (n, 2)), q.new_zeros(n, 2)), -1)
        return q, qd

    def _tip_minus_target(self, state):
        tip, target = self.mj_body_positions(state).unbind(1)
        return tip - target

    def _observation(self, state, ctrl):
        angles = state.q[:, :2]
        return torch.cat((torch.cos(angles), torch.sin(angles), state.q[:, 2:4], state.qd[:, :2],
                          self._tip_minus_target(state)), -1)

    def _goal_distance(self, state):
        return self._tip_minus_target(state).norm(dim=-1)

    def _reward(self, before, after, ctrl):
        return -self._goal_distance(after) - (ctrl * ctrl).sum(-1)


class Pusher(TorchsimEnv):
    """7-dof arm pushing an object on a table (``pusher.xml``; object and goal each on x/y slide joints),
    ``dt = 5 x 10 ms``.

    Observation (23): the 7 arm angles and rates, then the world positions of the arm's tip, the object and the
    goal. Action (7) in [-1, 1] mapped to ctrlrange [-2, 2]. Reward:
    ``-|object - goal| - 0.1 |ctrl|^2 - 0.5 |tip - object|``. No termination. Reset: the arm at its initial
    pose with rates U(-0.005, 0.005); the goal at the origin of its slides; the object uniform in
    [-0.3, 0] x [-0.2, 0.2] but at least 0.17 m from the goal (resampled up to 8 times, then pushed out radially).
    The object is a capsule (as in Brax); the wrist's two hinges share one body (``pusher.xml`` says why).
    Versus MuJoCo (1 s, wrist swept into the object): the object is pushed 0.64 m vs 0.56 m and the arm joints
    differ by up to 0.083 rad (MuJoCo's own timestep sensitivity: 0.0055 rad), from the wrist-object contact.
    """

    model_file = "pusher.xml"
    frame_skip = 5
    observation_size = 23
    min_goal_distance = 0.17

    named_bodies = ("tips_arm", "object", "goal")

    def _sample_init(self, n):
        q = self.init_q.expand(n, -1)
        low = torch.tensor([-0.3, -0.2], dtype=q.dtype, device=q.device)
        size = torch.tensor([0.3, 0.4], dtype=q.dtype, device=q.device)
        goal = q[:, -2:]
        obj = low + size * torch.rand(n, 2, dtype=q.dtype, device=q.device)
        for _ in range(8):  # fixed-count rejection sampling: no data-dependent loop
            retry = low + size * torch.rand(n, 2, dtype=q.dtype, device=q.device)
            too_close = (obj - goal).norm(dim=-1, keepdim=True) <= self.min_goal_distance
            obj = torch.where(too_close, retry, obj)
        away = obj - goal
        distance = away.norm(dim=-1, keepdim=True).clamp_min(1e-6)
        obj = torch.where(distance <= self.min_goal_distance, goal + away / distance * self.min_goal_distance, obj)
        q = torch.cat((q[:, :-4], obj, goal), -1)
        qd = torch.cat((self._noise(("uniform", 5e-3), (n, self.sys.nv - 4)), q.new_zeros(n, 4)), -1)
        return q, qd

    def _observation(self, state, ctrl):
        return torch.cat((state.q[:, :7], state.qd[:, :7], self.mj_body_positions(state).flatten(1)), -1)

    def _reward(self, before, after, ctrl):
        tip, obj, goal = self.mj_body_positions(after).unbind(1)
        return -(obj - goal).norm(dim=-1) - 0.1 * (ctrl * ctrl).sum(-1) - 0.5 * (tip - obj).norm(dim=-1)
