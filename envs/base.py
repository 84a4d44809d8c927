"""One TorchRL environment class for every torchsim task: specs, batched stepping, partial and native resets.

A task subclass names its model (MJCF, or URDF through ``torchsim.io_urdf``) and frame count and defines four
small functions of the simulator state: ``_sample_init`` (reset distribution), ``_observation``, ``_reward`` and
``_terminated``. Tasks with per-env goals that are not bodies of the model (a reach target, a target that respawns
when hit) keep them in ``self.task``, a ``(num_envs, task_size)`` tensor drawn by ``_sample_task`` at every reset
and advanced by ``_next_task`` after every step. Everything here is batched over ``num_envs`` and free of host
syncs (no ``.item()``, no boolean indexing, no data-dependent Python branches), so ``step`` and
``step_and_maybe_reset`` trace into one graph.
"""

import math
import pathlib

import mujoco
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

import torchsim
from torchsim.envs.pixels import PixelObservation
from torchsim.io_urdf import urdf_to_mjcf
from torchsim.state import State

ASSETS_DIR = pathlib.Path(__file__).parent / "assets"


def asset_path(name: str) -> pathlib.Path:
    """Return the path of a bundled asset (e.g. ``"ant.xml"``); raise FileNotFoundError if missing."""
    path = ASSETS_DIR / name
    if not path.is_file():
        available = sorted(p.name for p in ASSETS_DIR.iterdir() if p.is_file()) if ASSETS_DIR.is_dir() else []
        raise FileNotFoundError(f"asset {name!r} not found in {ASSETS_DIR}; available: {available}")
    return path


#: Randomisable physical parameters and what they scale (see ``TorchsimEnv.set_physics``).
PHYSICS_PARAMS = ("mass_scale", "friction_scale", "actuator_gain_scale")


def ring_points(center: torch.Tensor, r_min: float, r_span: float) -> torch.Tensor:
    """Points ``(n, 2)`` at a uniform random angle and a distance ``r_min + r_span U(0, 1)`` [m] from ``center
    (n, 2)``: where the target tasks put their targets."""
    radius = r_min + r_span * torch.rand_like(center[:, 0])
    angle = 2.0 * math.pi * torch.rand_like(center[:, 0])
    return center + radius[:, None] * torch.stack((torch.cos(angle), torch.sin(angle)), -1)


def select_state(mask: torch.Tensor, new: State, old: State) -> State:
    """Per env: ``new`` where ``mask (B,)`` is set, else ``old``."""
    return State(*(torch.where(mask.view((-1,) + (1,) * (n.ndim - 1)), n, o) for n, o in zip(new, old)))


class TorchsimEnv(EnvBase):
    """Base class of the torchsim tasks (a TorchRL ``EnvBase`` with ``batch_size=(num_envs,)``).

    Actions live in ``[-1, 1]^nu`` and map linearly onto each actuator's ``ctrlrange``; actions outside that box
    are clipped (the reward's control cost sees the clipped, mapped control). An env given a NaN or infinite action
    is not stepped under it: it runs with zero control and is flagged as diverged (below), not refused with an
    error, so one bad env does not stop the batch and the step needs no host sync. Each ``step`` advances the physics
    ``frame_skip`` times (``dt = frame_skip * timestep``). Episodes end when the task terminates, when the env's
    physics diverged (flagged by the engine; the env is frozen, reported ``terminated`` and reset like any other),
    or, as truncation, after ``episode_length`` steps.

    Args:
        num_envs: batch size.
        device, dtype: where and in which precision the physics and every emitted tensor live.
        episode_length: steps before truncation.
        native_autoreset: reset finished envs inside ``_step`` (TorchRL's native auto-reset path): the returned
            observation of a finished env is already its next episode's first one, and TorchRL writes NaN into
            its ``("next", "observation")``; use with ``GAE(..., auto_reset_env=True)``. This makes
            ``step_and_maybe_reset`` free of host syncs so it compiles as one graph.
        method, substeps, contact_model: physics solution method, substeps per model timestep and contact model
            (``torchsim.load_mjcf``; default: the task's ``method``, ``substeps`` and ``contact_model``).
        stagger_episodes: a full reset starts each env's step counter at a uniform draw in
            ``[0, episode_length)``, so first episodes are truncated at different times. Tasks that never end early
            otherwise run every env in the same phase of its episode, and a training batch of a few steps then
            holds one phase only (for training envs; evaluations want whole episodes).
        stepper: how the physics steps (``torchsim.Stepper``): ``"eager"`` (the reference step), ``"auto"`` (the
            fastest compiled strategy for the model) or a strategy name; or another env's ``stepper``, whose System
            and compiled step this env then shares (an evaluation env beside a training env compiles nothing).
        from_pixels: also emit camera images as ``pixels`` (``torchsim.envs.pixels``), rendered from the state
            after every step and reset. cameras: a model camera's name or index, a ``torchsim.render.Camera``, a
            list of these, or ``f(scene, mj_model)`` returning one (default: the task's, ``pixels.PIXEL_TASKS``).
            pixel_size: ``H = W`` or ``(H, W)``. pixel_kind: ``"rgb"`` (uint8, channels first) or ``"depth"``
            (float, metres); default: the task's. pixel_state: what ``observation`` holds beside the images:
            ``"full"`` (the state vector), ``"proprio"`` (the task's proprioceptive part) or ``"none"``.
            frame_stack: frames stacked on the channel axis. render_compile: ``render(..., compile=True)``.
            pixel_supersample: render ``k x k`` rays per pixel and average them (anti-aliased edges).
            pixel_privileged_state: also emit the full state vector as ``privileged_state``, for a critic trained
            in simulation (asymmetric actor-critic); the recipes' policies never read it.
    """

    #: The model asset in ``envs/assets``: MJCF (``.xml``) or URDF (``.urdf``, translated by ``urdf_to_mjcf``).
    model_file: str
    frame_skip: int
    #: Physics solution method (``torchsim.load_mjcf``) and XPBD projection passes, chosen per task.
    method: str = "spring"
    xpbd_iterations: int = 1
    #: URDF models only: rotor inertia [kg m^2] added to every joint (URDF has no armature).
    urdf_armature: float = 0.0
    #: Physics substeps per model timestep, chosen per task by measurement on its own method and contact model
    #: (None, or another method or contact model: ``load_mjcf``'s default).
    substeps: int | None = None
    #: Contact model (``torchsim.load_mjcf``'s ``contact_model``), chosen per task by measurement.
    contact_model: str = "impulse"
    #: Reset noise added to the initial ``q`` / ``qd``: (distribution, scale), distribution "uniform" (+-scale)
    #: or "normal" (standard deviation scale).
    noise_q = ("uniform", 0.1)
    noise_qd = ("normal", 0.1)
    #: MuJoCo bodies whose frames the task reads (``mj_body_positions``), in that order.
    named_bodies: tuple = ()
    #: Observation size (checked against ``_observation`` at construction).
    observation_size: int
    #: Goal-reaching tasks set this [m]: an episode succeeds when it ends with ``_goal_distance`` below it. The env
    #: then also emits ``goal_distance`` (B, 1) next to every observation (None: not a goal-reaching task).
    success_distance: float | None = None
    #: Floats of per-env task state (``self.task``) beside the physics; 0 for tasks whose goal is in the model.
    task_size: int = 0

    def __init__(self, num_envs: int = 1, *, device="cpu", dtype=torch.float32, episode_length: int = 1000,
                 native_autoreset: bool = False, method: str | None = None, substeps: int | None = None,
                 contact_model: str | None = None,
                 stagger_episodes: bool = False, stepper: "str | torchsim.Stepper" = "eager",
                 from_pixels: bool = False, cameras=None, pixel_size=48, pixel_kind: str | None = None,
                 pixel_state: str = "full", frame_stack: int = 1, render_compile: bool = False,
                 pixel_supersample: int = 1, pixel_privileged_state: bool = False):
        if int(num_envs) < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs}")
        super().__init__(device=device, batch_size=torch.Size([int(num_envs)]))
        xml = self._model_xml()
        self.mj_model = mujoco.MjModel.from_xml_string(xml)
        if isinstance(stepper, str):
            own_physics = (method or self.method, contact_model or self.contact_model) == (self.method,
                                                                                           self.contact_model)
            if substeps is None and own_physics:  # the task's substeps were measured on its own physics
                substeps = self.substeps
            system = torchsim.load_mjcf(xml, method=method or self.method, substeps=substeps,
                                        contact_model=contact_model or self.contact_model,
                                        xpbd_iterations=self.xpbd_iterations, dtype=dtype, device=self.device)
            stepper = torchsim.Stepper(system, stepper)
        elif ((stepper.sys.dtype, stepper.sys.device) != (dtype, self.device) or method or substeps is not None
              or contact_model):
            raise ValueError(f"{type(self).__name__}: a given stepper's System must be in the env's dtype and on its "
                             f"device ({dtype}, {self.device}; got {stepper.sys.dtype}, {stepper.sys.device}) and "
                             "comes with its own method, substeps and contact model")
        self.base_sys = stepper.sys
        self.stepper = stepper
        self.episode_length = int(episode_length)
        self.stagger_episodes = bool(stagger_episodes)
        self.dt = self.frame_skip * self.sys.timestep
        self._free_quat_qpos = [int(a) + 3 for a in self.sys.free_qpos]  # Python ints: no sync at step time
        if native_autoreset:
            self.__dict__["_torchrl_native_autoreset"] = True
        self._named_body_ids = [self.mj_body_id(name) for name in self.named_bodies]
        keyframe = self.mj_model.key_qpos[0] if self.mj_model.nkey else self.mj_model.qpos0
        self.register_buffer("init_q", torch.as_tensor(keyframe, dtype=dtype, device=self.device))
        ctrl_range = torch.as_tensor(self.mj_model.actuator_ctrlrange, dtype=dtype, device=self.device)
        self.register_buffer("ctrl_low", ctrl_range[:, 0])
        self.register_buffer("ctrl_high", ctrl_range[:, 1])
        self._setup()
        #: What adds to the task's observation, told where the env's state changes (``PixelObservation``: ``start``,
        #: ``advance``, ``fields``, ``add_specs``, ``episode_state``): a pixel env's images (``pixel_obs``), or none.
        self.observers = []
        self.pixel_obs = None
        if from_pixels:
            self.pixel_obs = PixelObservation(self, cameras, pixel_size, pixel_kind, pixel_state, frame_stack,
                                              render_compile, pixel_supersample, pixel_privileged_state)
            self.observers.append(self.pixel_obs)
        elif pixel_privileged_state:
            raise ValueError(f"{type(self).__name__}: pixel_privileged_state needs from_pixels=True (without images "
                             "the observation is the full state already)")
        self._make_specs(dtype)
        self.state = self._initial_state()
        self.task = self._sample_task(self.state)
        self._start_pool: State | None = None  # start states drawn ahead for restarts (_pooled_starts)
        self._start_pool_used = 0
        for observer in self.observers:
            observer.start(self.state)
        obs = self._observation(self.state, self._zero_ctrl())
        if obs.shape != (*self.batch_size, self.observation_size):
            raise RuntimeError(f"{type(self).__name__}: observation has shape {tuple(obs.shape)}, expected "
                               f"{(*self.batch_size, self.observation_size)}")
        self.register_buffer("step_count", torch.zeros(self.batch_size, dtype=torch.long, device=self.device))

    # ----------------------------------------------------------------------------------------------- task hooks
    def _model_xml(self) -> str:
        """MJCF text of the simulated model (MuJoCo's ``MjModel`` and the torchsim ``System`` are both built from
        it): the MJCF asset, or the URDF asset translated by ``urdf_to_mjcf`` with ``urdf_armature``."""
        path = asset_path(self.model_file)
        if path.suffix == ".urdf":
            return urdf_to_mjcf(path, armature=self.urdf_armature)
        return path.read_text()

    def _setup(self) -> None:
        """Precompute task constants that depend on the loaded model (``self.sys``, ``self.mj_model``); called
        once, before the first reset. Default: nothing."""

    def _sample_init(self, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Initial ``q (n, nq)`` and ``qd (n, nv)`` of fresh episodes: the model's first keyframe (else qpos0)
        plus ``noise_q`` / ``noise_qd``; free-joint quaternions are renormalised."""
        q = self.init_q.expand(n, -1) + self._noise(self.noise_q, (n, self.sys.nq))
        qd = self._noise(self.noise_qd, (n, self.sys.nv))
        for adr in self._free_quat_qpos:
            quat = q[:, adr:adr + 4]
            q = torch.cat((q[:, :adr], quat / quat.norm(dim=-1, keepdim=True), q[:, adr + 4:]), -1)
        return q, qd

    def _sample_task(self, state: State) -> torch.Tensor:
        """Task state ``(n, task_size)`` of fresh episodes starting in ``state`` (n envs); default: none."""
        return state.q.new_zeros(state.q.shape[0], self.task_size)

    def _next_task(self, state: State, task: torch.Tensor) -> torch.Tensor:
        """Task state after a step ended in ``state`` (e.g. a hit target respawned); default: unchanged. The step's
        reward saw the old one, the returned observation sees the new one."""
        return task

    def _observation(self, state: State, ctrl: torch.Tensor) -> torch.Tensor:
        """Observation ``(B, observation_size)`` in ``state``, reached under controls ``ctrl (B, nu)`` (zero at the
        start of an episode)."""
        raise NotImplementedError

    def _reward(self, before: State, after: State, ctrl: torch.Tensor) -> torch.Tensor:
        """Reward ``(B,)`` of the transition ``before -> after`` under (clipped, mapped) controls ``ctrl``."""
        raise NotImplementedError

    def _terminated(self, state: State) -> torch.Tensor:
        """``(B,)`` bool: the episode ended in ``state`` (default: never)."""
        return torch.zeros_like(state.diverged)

    def _goal_distance(self, state: State) -> torch.Tensor:
        """``(B,)`` distance [m] between the effector and the goal (tasks that set ``success_distance``)."""
        raise NotImplementedError

    # -------------------------------------------------------------------------------------------------- helpers
    def _noise(self, spec, shape) -> torch.Tensor:
        kind, scale = spec
        dtype = self.sys.dtype
        if kind == "uniform":
            return scale * (2.0 * torch.rand(shape, dtype=dtype, device=self.device) - 1.0)
        return scale * torch.randn(shape, dtype=dtype, device=self.device)

    def _initial_state(self, n: int | None = None) -> State:
        """Fresh start states of ``n`` envs (default: all of them)."""
        q, qd = self._sample_init(self.batch_size[0] if n is None else n)
        return torchsim.init(self.base_sys, q, qd)  # kinematics only: per-env (batchable) parameters play no part

    def _pooled_starts(self, n: int) -> State:
        """``n`` fresh start states, taken in order from a pool drawn a batch at a time (each state used once).

        A start state's kinematics run as ~100 small ops however few envs restart, so drawing them for the 1-10
        envs that end in a 2048-env Ant step cost ~9% of a collector batch; from a pool of a batch's size they cost
        one slice, plus a refill every few hundred steps."""
        if self._start_pool is None or self._start_pool_used + n > self._start_pool.q.shape[0]:
            self._start_pool, self._start_pool_used = self._initial_state(max(n, self.batch_size[0])), 0
        used, self._start_pool_used = self._start_pool_used, self._start_pool_used + n
        return State(*(x[used:used + n] for x in self._start_pool))

    def _ctrl(self, action: torch.Tensor) -> torch.Tensor:
        """Clip ``action`` to [-1, 1] and map it onto the actuators' control ranges."""
        action = action.clamp(-1.0, 1.0)
        return self.ctrl_low + 0.5 * (action + 1.0) * (self.ctrl_high - self.ctrl_low)

    def _zero_ctrl(self) -> torch.Tensor:
        return torch.zeros((*self.batch_size, self.sys.nu), dtype=self.sys.dtype, device=self.device)

    def _check_action(self, action: torch.Tensor) -> None:
        expected = (*self.batch_size, self.sys.nu)
        if tuple(action.shape) != expected:
            raise ValueError(f"{type(self).__name__}: action must have shape {expected}, got {tuple(action.shape)}")
        if action.dtype != self.sys.dtype:
            raise ValueError(f"{type(self).__name__}: action must have dtype {self.sys.dtype}, got {action.dtype}")
        if action.device != self.device:
            raise ValueError(f"{type(self).__name__}: action is on {action.device}, the env on {self.device}")

    def _make_specs(self, dtype) -> None:
        shape, dev = self.batch_size, self.device
        self.observation_spec = Composite(
            observation=Unbounded((*shape, self.observation_size), dtype=dtype, device=dev), shape=shape)
        if self.success_distance is not None:
            self.observation_spec["goal_distance"] = Unbounded((*shape, 1), dtype=dtype, device=dev)
        self.action_spec = Bounded(-1.0, 1.0, (*shape, self.sys.nu), dtype=dtype, device=dev)
        for observer in self.observers:
            observer.add_specs(self.observation_spec, self.observation_size)
        self.reward_spec = Unbounded((*shape, 1), dtype=dtype, device=dev)
        flag = lambda: Categorical(2, (*shape, 1), dtype=torch.bool, device=dev)  # noqa: E731
        self.full_done_spec = Composite(done=flag(), terminated=flag(), truncated=flag(), shape=shape)

    def _output(self, state: State, ctrl: torch.Tensor, **fields) -> TensorDict:
        """The TensorDict an env emits in ``state`` reached under ``ctrl``: observation (+ goal distance) and
        ``fields``."""
        if self.success_distance is not None:
            fields["goal_distance"] = self._goal_distance(state)[:, None]
        entries = {"observation": self._observation(state, ctrl)}
        for observer in self.observers:
            entries = observer.fields(entries)
        return TensorDict(**entries, **fields, batch_size=self.batch_size, device=self.device)

    # ---------------------------------------------------------------------------------------------- public API
    def set_state(self, q: torch.Tensor, qd: torch.Tensor, task: torch.Tensor | None = None) -> torch.Tensor:
        """Put every env at ``q (B, nq)``, ``qd (B, nv)`` (MuJoCo layout) and, if given, task state ``task
        (B, task_size)`` (else freshly drawn), restart its episode; return the obs. NaN or infinite values are
        refused (ValueError naming the argument and the envs): unlike a policy's bad action mid-episode, a bad
        start state is the caller's to fix, not a divergence to flag."""
        for name, value in (("q", q), ("qd", qd), ("task", task)):
            if value is not None and not bool(torch.isfinite(value).all()):
                envs = (~torch.isfinite(value)).reshape(value.shape[0], -1).any(-1).nonzero().flatten().tolist()
                raise ValueError(f"set_state: {name} holds NaN or infinite values (envs {envs})")
        self.state = torchsim.init(self.sys, q, qd)
        if task is None:
            task = self._sample_task(self.state)
        elif tuple(task.shape) != (*self.batch_size, self.task_size):
            raise ValueError(f"task must have shape {(*self.batch_size, self.task_size)}, got {tuple(task.shape)}")
        self.task = task.to(device=self.device, dtype=self.sys.dtype)
        self.step_count.zero_()
        for observer in self.observers:
            observer.start(self.state)
        return self._observation(self.state, self._zero_ctrl())

    def set_physics(self, **scales) -> None:
        """Per-env physical parameters for domain randomisation, as multiples of the model's values.

        Keywords (each a scalar or a ``(num_envs,)`` tensor; omitted ones return to 1): ``mass_scale`` (every
        body's mass and inertia), ``friction_scale`` (every contact pair's sliding friction),
        ``actuator_gain_scale`` (every actuator's strength: its gain and its bias terms together, so a position
        servo's ``kp`` and ``kv`` scale and its set point stays where the control puts it). The model is not
        rebuilt. Each scale must be finite and positive (ValueError naming the parameter): a zero mass or gain, or a
        negative one, is no physical body or motor.
        """
        unknown = set(scales) - set(PHYSICS_PARAMS)
        if unknown:
            raise ValueError(f"unknown physics parameter(s) {sorted(unknown)}; expected some of {PHYSICS_PARAMS}")
        b = self.base_sys.replace(mocap_pos=self.sys.mocap_pos, mocap_quat=self.sys.mocap_quat)  # set_mocap's stay
        s = {k: torch.as_tensor(scales.get(k, 1.0), dtype=b.dtype, device=self.device).expand(self.batch_size)
             for k in PHYSICS_PARAMS}
        for name, scale in s.items():
            if not bool((torch.isfinite(scale) & (scale > 0)).all()):
                raise ValueError(f"set_physics: {name} must be finite and positive, got {scales[name]}")
        mass = s["mass_scale"][:, None]
        self.stepper = self.stepper.for_system(b.replace(
            body_mass=b.body_mass * mass, body_inertia=b.body_inertia * mass[..., None, None],
            act_gain=b.act_gain * s["actuator_gain_scale"][:, None],
            act_bias=b.act_bias * s["actuator_gain_scale"][:, None, None],
            contact_groups=tuple(g._replace(friction=g.friction * s["friction_scale"][:, None])
                                 for g in b.contact_groups)))

    def set_mocap(self, pos=None, quat=None) -> None:
        """Per-env poses of the model's ``M`` mocap bodies, the targets their welds pull bodies to: ``pos``
        ``(num_envs, M, 3)`` [m] and ``quat`` ``(num_envs, M, 4)`` (``wxyz``, normalised as MuJoCo normalises
        ``mocap_quat``), world frame, as MuJoCo's ``mocap_pos`` and ``mocap_quat``; one left out keeps its values.
        They are inputs of the compiled step (moving them rebuilds nothing), and ``set_physics`` keeps them."""
        sys, values = self.sys, {}
        for name, value, width in (("mocap_pos", pos, 3), ("mocap_quat", quat, 4)):
            if value is None:
                continue
            value = torch.as_tensor(value, dtype=sys.dtype, device=self.device)
            shape = (*self.batch_size, sys.mocap_pos.shape[-2], width)
            if value.shape != shape:
                raise ValueError(f"set_mocap: {name} must have shape {shape} (envs, mocap bodies, {width}), got "
                                 f"{tuple(value.shape)}")
            if not bool(torch.isfinite(value).all()):
                raise ValueError(f"set_mocap: {name} must be finite")
            values[name] = value / value.norm(dim=-1, keepdim=True) if name == "mocap_quat" else value
        self.stepper = self.stepper.for_system(sys.replace(**values))

    def episode_state(self) -> dict:
        """The running episodes, as tensors: physics state, task, step counts, the start states drawn ahead for
        restarts (``_pooled_starts``) and a pixel env's frame stacks. ``load_episode_state`` puts them back, and the
        episodes go on as they would have (a training checkpoint holds them, so that a resumed run continues)."""
        saved = {"state": self.state._asdict(), "task": self.task, "step_count": self.step_count}
        if self._start_pool is not None:
            saved["start_pool"], saved["start_pool_used"] = self._start_pool._asdict(), self._start_pool_used
        for observer in self.observers:  # a pixel env's frame stacks
            saved.update(observer.episode_state())
        return saved

    def load_episode_state(self, saved: dict) -> None:
        """Continue the episodes of ``saved`` (``episode_state``, of an env of this task and batch)."""
        self.state, self.task = State(**saved["state"]), saved["task"]
        self.step_count.copy_(saved["step_count"])
        pool = saved.get("start_pool")
        self._start_pool = None if pool is None else State(**pool)
        self._start_pool_used = saved.get("start_pool_used", 0)
        for observer in self.observers:
            observer.load_episode_state(saved)

    @property
    def sys(self) -> "torchsim.System":
        """The System the env steps: ``base_sys``, with per-env parameters after ``set_physics``."""
        return self.stepper.sys

    def _set_seed(self, seed: int | None) -> None:
        # The global generator: an explicit torch.Generator would break fullgraph compilation of the step.
        if seed is not None:
            torch.manual_seed(seed)
            self._start_pool = None  # drawn before the seed: a seeded run must not reuse it

    def _reset(self, tensordict: TensorDictBase | None, **kwargs) -> TensorDictBase:
        mask = None if tensordict is None else tensordict.get("_reset", None)
        if mask is None:
            self.state = self._initial_state()
            self.task = self._sample_task(self.state)
            if self.stagger_episodes:
                self.step_count.copy_(torch.randint_like(self.step_count, self.episode_length))
            else:
                self.step_count.zero_()
            for observer in self.observers:
                observer.start(self.state)
        else:
            # Start states for the flagged envs only: building them for every env cost a 2048-env Ant collector
            # step ~9 ms, more than its share of the physics, to restart a few envs.
            rows = mask.reshape(self.batch_size).nonzero().squeeze(-1)
            fresh = self._pooled_starts(rows.numel())
            self.state = State(*(old.index_copy(0, rows, new) for old, new in zip(self.state, fresh)))
            self.task = self.task.index_copy(0, rows, self._sample_task(fresh))
            self.step_count.index_fill_(0, rows, 0)
            for observer in self.observers:
                observer.start(self.state, rows=rows)
        no = torch.zeros((*self.batch_size, 1), dtype=torch.bool, device=self.device)
        return self._output(self.state, self._zero_ctrl(), done=no, terminated=no.clone(), truncated=no.clone())

    def _advance(self, state: State, task: torch.Tensor, ctrl: torch.Tensor, steps: torch.Tensor,
                 bad: torch.Tensor | None = None):
        """One env step from ``state``, ``task`` and the episodes' step counts ``steps (B,)`` under ``ctrl``, as plain
        tensors, writing nothing to the env (so it is differentiable: ``torchsim.algos.apg`` unrolls it): the new
        state and task, the reward (``_diverged_reward`` where the physics diverged), terminated (the task's, or diverged; ``bad
        (B,)`` marks envs to treat as diverged), truncated and the new step counts."""
        before = state
        stepper, physics_ctrl = self._physics_inputs(state, ctrl)
        for _ in range(self.frame_skip):
            state = stepper(state, physics_ctrl)
        if bad is not None:
            state = state._replace(diverged=state.diverged | bad)
        steps = steps + 1
        reward = torch.where(state.diverged, self._diverged_reward(steps), self._reward(before, state, ctrl))
        terminated = self._terminated(state) | state.diverged
        task = self._next_task(state, task)
        return state, task, reward, terminated, steps >= self.episode_length, steps

    def _physics_inputs(self, state: State, ctrl: torch.Tensor):
        """``(stepper, controls)`` the physics steps under for action ``ctrl`` from ``state``: the env's stepper and
        ``ctrl`` itself; a task that drives its robot otherwise (FetchReach: mocap targets) returns its own."""
        return self.stepper, ctrl

    def _diverged_reward(self, steps: torch.Tensor):
        """The reward of a step whose physics diverged (the episode then ends), ``steps (B,)`` the episodes' step
        counts after it: 0. A task whose rewards are never positive scores it lower, or ending would pay."""
        return 0.0

    def compile_step(self, **options) -> None:
        """Run :meth:`_advance` (physics, reward, termination, task: a step's arithmetic) as ``torch.compile(**options)``
        compiles it: a ``kernel`` stepper is one operator of its graph (``torchsim.execution.step_op``) and the small
        ops around it fuse; with ``mode="reduce-overhead"`` on a GPU, a CUDA graph replays the whole of it."""
        compiled = torch.compile(self._advance, **options)

        def advance(*args):
            # A CUDA graph writes its outputs into memory that its next replay reuses: each call begins a new step,
            # and what the env keeps (the state, the reward the collector stores) is copied out (no-ops elsewhere,
            # and a few small copies)
            torch.compiler.cudagraph_mark_step_begin()
            return torch.utils._pytree.tree_map(torch.clone, compiled(*args))

        self._advance = advance

    def _restart(self, done: torch.Tensor, state: State, task: torch.Tensor, steps: torch.Tensor,
                 ctrl: torch.Tensor):
        """The envs of ``done (B,)`` at fresh start states and tasks, step count 0 and no control (what their first
        observation sees); the others as they are."""
        fresh = self._initial_state()
        return (select_state(done, fresh, state), torch.where(done[:, None], self._sample_task(fresh), task),
                torch.where(done, 0, steps), torch.where(done[:, None], 0.0, ctrl))

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action")
        self._check_action(action)
        # A non-finite action (e.g. from a policy that diverged) must reach neither the physics nor the observation:
        # the env runs with zero control and is flagged as diverged, so it ends and resets like one. Checked before
        # clipping, which would turn +-inf into a full +-1 command; one fused reduction, no host sync.
        bad_action = ~torch.isfinite(action).all(-1)
        ctrl = torch.where(bad_action[:, None], 0.0, self._ctrl(action))
        state, task, reward, terminated, truncated, steps = self._advance(self.state, self.task, ctrl,
                                                                          self.step_count, bad_action)
        done = terminated | truncated
        if self.__dict__.get("_torchrl_native_autoreset", False):
            state, task, steps, ctrl = self._restart(done, state, task, steps, ctrl)
        self.step_count.copy_(steps)
        self.state, self.task = state, task
        for observer in self.observers:  # with native auto-reset, the finished envs' stacks restart
            observer.advance(state, restart=done if self.__dict__.get("_torchrl_native_autoreset", False) else None)
        return self._output(state, ctrl, reward=reward[:, None].to(self.sys.dtype), done=done[:, None],
                            terminated=terminated[:, None], truncated=truncated[:, None])

    def mj_body_id(self, name: str) -> int:
        """Index of the MuJoCo body ``name`` (for :func:`torchsim.mj_body_poses`); a clear error if absent."""
        body = mujoco.mj_name2id(self.mj_model, mujoco.mjtObj.mjOBJ_BODY, name)
        if body < 0:
            raise ValueError(f"{self.model_file} has no body named {name!r}")
        return body

    def mj_body_poses(self, state: State) -> tuple[torch.Tensor, torch.Tensor]:
        """World positions ``(B, K, 3)`` and orientations ``(B, K, 4)`` of the K ``named_bodies``' frames."""
        pos, quat = torchsim.mj_body_poses(self.sys, state.x_pos, state.x_quat)
        return pos[:, self._named_body_ids], quat[:, self._named_body_ids]

    def mj_body_positions(self, state: State) -> torch.Tensor:
        """World positions ``(B, K, 3)`` of the K ``named_bodies``' frames (fused bodies included)."""
        return self.mj_body_poses(state)[0]
