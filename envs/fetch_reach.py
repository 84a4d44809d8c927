"""gymnasium-robotics' FetchReach (v4, ``gymnasium_robotics.envs.fetch.reach``) on the Fetch mesh robot as the package
ships it: the arm is moved by a mocap body welded to its gripper, and the task is to bring the gripper's ``robot0:grip``
site within 5 cm of a goal. The model comes from the installed package (``pip install -e '.[robotics]'``), not from
this repository."""

import importlib.util
import pathlib
import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import torch

from torchsim import spatial
from torchsim.envs.base import TorchsimEnv

#: The package version whose model and task definition this env reproduces.
GYMNASIUM_ROBOTICS = "gymnasium_robotics-1.4.2"
#: Where ``studies/check_third_party.py`` unpacks the wheel (the fallback when the package is not installed).
CACHE_DIR = pathlib.Path.home() / ".cache" / "torchsim" / "third_party" / f"{GYMNASIUM_ROBOTICS}-py3-none-any"
MODEL = pathlib.Path("envs") / "assets" / "fetch" / "reach.xml"

# FetchReach's definition (reach.py, fetch_env.py, robot_env.py, utils/mujoco_utils.py of gymnasium-robotics 1.4.2)
INITIAL_QPOS = {"robot0:slide0": 0.4049, "robot0:slide1": 0.48, "robot0:slide2": 0.0}
GRIPPER_OFFSET = (-0.498, 0.005, -0.431)  # the initial mocap target, from the initial grip site, plus...
GRIPPER_EXTRA_HEIGHT = 0.2  # ...this much higher [m]
GRIPPER_ROTATION = (1.0, 0.0, 1.0, 0.0)  # the fixed mocap orientation (added to the gripper's quaternion each step)
SETTLE_STEPS = 10  # env steps the arm settles under the initial mocap target
ACTION_SCALE = 0.05  # [m] mocap displacement of a full action
TARGET_RANGE = 0.15  # [m] goal = initial grip position + U(-range, range)^3
DISTANCE_THRESHOLD = 0.05  # [m]
EPISODE_STEPS = 50  # FetchReach-v4's max_episode_steps
DIVERGED_DISTANCE = 0.5  # [m] per remaining step of a diverged episode (beyond any distance in the reach's cube)
FINGERS = ("robot0:r_gripper_finger_joint", "robot0:l_gripper_finger_joint")


def reach_xml_path() -> pathlib.Path:
    """``fetch/reach.xml`` of the installed gymnasium-robotics (found without importing it, which would import
    gymnasium), else of the unpacked wheel in ``CACHE_DIR``; a clear error naming the install command otherwise."""
    spec = importlib.util.find_spec("gymnasium_robotics")
    candidates = [pathlib.Path(spec.origin).parent / MODEL] if spec is not None and spec.origin else []
    candidates.append(CACHE_DIR / "gymnasium_robotics" / MODEL)
    for path in candidates:
        if path.is_file():
            return path
    raise FileNotFoundError(f"FetchReach needs gymnasium-robotics' Fetch model ({GYMNASIUM_ROBOTICS}); install it with "
                            f"pip install -e '.[robotics]' (looked in: {', '.join(map(str, candidates))})")


def _inline_includes(element: ET.Element, folder: pathlib.Path) -> None:
    """Replace every ``<include file=...>`` below ``element`` by the children of the included file's root."""
    for child in list(element):
        if child.tag == "include":
            included = ET.parse(folder / child.get("file")).getroot()
            _inline_includes(included, folder)
            at = list(element).index(child)
            element.remove(child)
            for offset, part in enumerate(included):
                element.insert(at + offset, part)
        else:
            _inline_includes(child, folder)


def reach_model(path: pathlib.Path, max_hull_vertices: int = 64, contacts: bool = False) -> str:
    """The MJCF text of ``reach.xml`` as one string MuJoCo and torchsim compile alike: includes inlined, mesh and
    texture folders absolute, every mesh's hull capped at ``max_hull_vertices`` (MuJoCo's ``maxhullvert``, what
    ``load_mjcf(max_hull_vertices=64)`` does: MuJoCo then collides the same hulls), the weld's ``relpose`` the
    identity (what the package's ``reset_mocap_welds`` writes into ``eq_data`` before anything runs) and, unless
    ``contacts``, contacts disabled (``FetchReach``)."""
    root = ET.parse(path).getroot()
    _inline_includes(root, path.parent)
    compiler = root.find("compiler")
    for key in ("meshdir", "texturedir"):
        compiler.set(key, str((path.parent / compiler.get(key)).resolve()))
    for mesh in root.iter("mesh"):
        mesh.set("maxhullvert", str(max_hull_vertices))
    welds = list(root.iter("weld"))
    if len(welds) != 1:
        raise ValueError(f"{path}: expected one weld (mocap to gripper), found {len(welds)}")
    welds[0].set("relpose", "0 0 0 1 0 0 0")
    if not contacts:
        option = root.find("option")
        flag = option.find("flag")
        flag = ET.SubElement(option, "flag") if flag is None else flag
        flag.set("contact", "disable")
    return ET.tostring(root, encoding="unicode")


def settled_state(m: mujoco.MjModel, n_substeps: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The package's ``_env_setup`` in MuJoCo: the base's slides at ``INITIAL_QPOS``, the mocap target
    ``GRIPPER_OFFSET`` + ``GRIPPER_EXTRA_HEIGHT`` from the grip site at ``GRIPPER_ROTATION``, ``SETTLE_STEPS`` env
    steps; returns ``qpos``, ``qvel`` (every episode starts there) and the grip site's position (goals are drawn
    around it)."""
    d = mujoco.MjData(m)
    for name, value in INITIAL_QPOS.items():
        d.qpos[m.joint(name).qposadr[0]] = value
    mujoco.mj_forward(m, d)
    grip = m.site("robot0:grip").id
    d.mocap_pos[0] = np.array(GRIPPER_OFFSET) + np.array([0.0, 0.0, GRIPPER_EXTRA_HEIGHT]) + d.site_xpos[grip]
    d.mocap_quat[0] = GRIPPER_ROTATION
    for _ in range(SETTLE_STEPS):
        mujoco.mj_step(m, d, nstep=n_substeps)
    return d.qpos.copy(), d.qvel.copy(), d.site_xpos[grip].copy()


class FetchReach(TorchsimEnv):
    """FetchReach (``FetchReachDense-v4``; ``reward_type="sparse"``: ``FetchReach-v4``): the Fetch robot of
    gymnasium-robotics 1.4.2 (its meshes, hulls capped at 64 vertices) moves its gripper to a goal; ``dt = 20 x 2 ms``,
    50 steps an episode (the package's ``max_episode_steps``).

    As the package defines it: the action (4, in [-1, 1]) moves the mocap body welded to ``robot0:gripper_link``
    to the gripper's current position plus ``0.05 a[:3]`` m, at the gripper's current orientation plus ``(1, 0, 1,
    0)`` (normalised); ``a[3]`` (the gripper) is ignored (``block_gripper``). Every episode starts from the state the
    package settles the arm into (:func:`settled_state`, computed in MuJoCo); the goal is the initial grip site
    position plus U(-0.15, 0.15)^3. Reward: ``-d`` (dense) or ``-(d > 0.05)`` (sparse), ``d`` the grip site's
    distance to the goal after the step; success: ``d < 0.05`` at the episode's end. No termination, except where
    the physics diverged (torchsim's flag, as in every task), which the package's MuJoCo never does: that step scores
    the worst the rest of the episode could, ``-0.5`` m (sparse: ``-1``) for each step left including it, not
    the base class's 0, which a reward that is never positive turns into a prize (a policy trained with it learnt
    to blow the arm up: episodes of 14 steps, 23% success).

    Another departure: the package puts the finger slides back at 0 after every step (``_step_callback``); here they are
    left where they are (no actuator, no contact).
    Resetting them through ``torchsim.init`` rebuilds the whole arm from its joint angles and undoes the give of
    torchsim's joints under the weld's pull: the gripper then moved a tenth as far per step as MuJoCo's.

    Observation (16): the package's ``observation`` (grip site position, the two finger slides, the grip site's
    velocity times dt, the finger rates times dt), its ``desired_goal``, and goal minus grip site.

    Simplification: contacts are disabled (``reach_model``). The package's model collides the robot's 64-vertex
    hulls with each other, the table and the floor, and an eager step of those mesh pairs costs seconds here; in the
    reach the only contact the task can make is the gripper touching the table, whose top (z = 0.4 m) is 1.5 cm above
    the lowest goals. MuJoCo's evaluation (``physics=mujoco``) runs the same contact-free model.

    Versus MuJoCo (same model, the package's action law, ``tests/test_fetch_reach.py``): the grip site within
    0.1-1.4 mm of the package's over 6 random full-range actions, while the package's path moves 5-9 cm. Under
    uniform random actions no env diverges (64 envs, 50 steps), and the gripper turns further from the orientation
    the mocap law holds than MuJoCo's does (median 0.078 rad against 0.013): the joints give under the weld's pull.
    """

    frame_skip = 20
    substeps = 1  # 2 ms, MuJoCo's timestep: closest to MuJoCo (tests/test_fetch_reach.py) and cheapest
    noise_q = ("uniform", 0.0)
    noise_qd = ("normal", 0.0)
    named_bodies = ("robot0:gripper_link",)
    observation_size = 16
    task_size = 3
    success_distance = DISTANCE_THRESHOLD
    action_size = 4

    def __init__(self, num_envs: int = 1, *, reward_type: str = "dense", **kwargs):
        if reward_type not in ("dense", "sparse"):
            raise ValueError(f"reward_type must be 'dense' or 'sparse', got {reward_type!r}")
        self.reward_type = reward_type
        kwargs.setdefault("episode_length", EPISODE_STEPS)
        super().__init__(num_envs, **kwargs)

    def _model_xml(self):
        return reach_model(reach_xml_path())

    def _setup(self):
        m, sys = self.mj_model, self.sys
        if (m.nmocap, m.nu) != (1, 0):
            raise RuntimeError("FetchReach expects one mocap body and no actuators")
        q, qd, grip = settled_state(m, self.frame_skip)
        as_tensor = lambda x: torch.as_tensor(x, dtype=sys.dtype, device=self.device)  # noqa: E731
        self.start_q, self.start_qd, self.initial_grip = as_tensor(q), as_tensor(qd), as_tensor(grip)
        gripper = self._named_body_ids[0]
        self.gripper_ext = int(sys.mjbody_body[gripper])  # the ext body the gripper is fused into
        self.grip_offset = as_tensor(m.site_pos[m.site("robot0:grip").id])  # in the gripper's frame
        self.finger_qpos = [int(m.joint(name).qposadr[0]) for name in FINGERS]
        self.finger_dof = [int(m.joint(name).dofadr[0]) for name in FINGERS]
        self.mocap_turn = as_tensor(GRIPPER_ROTATION)

    # the action is not an actuator control (the model has none): it moves the mocap target
    def _make_specs(self, dtype):
        super()._make_specs(dtype)
        self.action_spec = self.action_spec.__class__(-1.0, 1.0, (*self.batch_size, self.action_size), dtype=dtype,
                                                      device=self.device)

    def _check_action(self, action):
        expected = (*self.batch_size, self.action_size)
        if tuple(action.shape) != expected:
            raise ValueError(f"FetchReach: action must have shape {expected}, got {tuple(action.shape)}")
        if action.dtype != self.sys.dtype:
            raise ValueError(f"FetchReach: action must have dtype {self.sys.dtype}, got {action.dtype}")

    def _ctrl(self, action):
        return action.clamp(-1.0, 1.0)

    def _zero_ctrl(self):
        return torch.zeros((*self.batch_size, self.action_size), dtype=self.sys.dtype, device=self.device)

    def _sample_init(self, n):
        return self.start_q.expand(n, -1), self.start_qd.expand(n, -1)

    def _sample_task(self, state):
        n = state.q.shape[0]
        draw = torch.rand(n, 3, dtype=state.q.dtype, device=self.device)
        return self.initial_grip + TARGET_RANGE * (2.0 * draw - 1.0)

    def mocap_target(self, state, action):
        """The package's ``mocap_set_action``: mocap ``(B, 1, 3)``, ``(B, 1, 4)`` at the gripper's pose moved by
        ``ACTION_SCALE action[:, :3]`` and turned by adding ``GRIPPER_ROTATION`` to its quaternion."""
        pos, quat = self.mj_body_poses(state)
        mocap_quat = quat[:, 0] + self.mocap_turn
        return ((pos[:, 0] + ACTION_SCALE * action[:, :3])[:, None],
                (mocap_quat / mocap_quat.norm(dim=-1, keepdim=True))[:, None])

    def _physics_inputs(self, state, ctrl):
        """The action moves the mocap target (``mocap_target``); the model has no actuators to control."""
        mocap_pos, mocap_quat = self.mocap_target(state, ctrl)
        return self.stepper.for_system(self.sys.replace(mocap_pos=mocap_pos, mocap_quat=mocap_quat)), ctrl[:, :0]

    def _diverged_reward(self, steps):
        """The worst the rest of the episode could score, ``DIVERGED_DISTANCE`` (sparse: 1) lost for each step left
        including this one: left at 0, a reward that is never positive would make blowing up the physics the best
        move (a policy trained so learnt it)."""
        worst = -(self.episode_length - steps + 1).to(self.sys.dtype)
        return worst * DIVERGED_DISTANCE if self.reward_type == "dense" else worst

    def grip_site(self, state):
        """World position ``(B, 3)`` of the ``robot0:grip`` site."""
        pos, quat = self.mj_body_poses(state)
        return pos[:, 0] + spatial.batch_first.quat_rotate(quat[:, 0], self.grip_offset)

    def _observation(self, state, ctrl):
        grip = self.grip_site(state)
        k = self.gripper_ext
        velocity = state.xd_vel[:, k] + torch.linalg.cross(state.xd_ang[:, k], grip - state.x_pos[:, k])
        fingers, finger_rates = state.q[:, self.finger_qpos], state.qd[:, self.finger_dof]
        return torch.cat((grip, fingers, velocity * self.dt, finger_rates * self.dt, self.task, self.task - grip), -1)

    def _goal_distance(self, state):
        return (self.task - self.grip_site(state)).norm(dim=-1)

    def _reward(self, before, after, ctrl):
        distance = self._goal_distance(after)
        if self.reward_type == "sparse":
            return -(distance > DISTANCE_THRESHOLD).to(distance.dtype)
        return -distance
