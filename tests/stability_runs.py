"""The runs behind docs/stability.md that ``tests/test_stability.py`` asserts and the studies chart or tabulate: the
hanging chain of ``studies/stability_map.py`` (its model, starts and bounds; the module docstring there has the
reading), an env at its defaults under random actions, and the soak of ``studies/soak.py`` (an env stepping through
a :class:`DivergenceWatch`, under one of ``MODES``)."""

import inspect
import math
import time

import torch
from tensordict import TensorDict
from torchrl.envs.utils import step_mdp

import torchsim
from torchsim import rigid
from torchsim.envs import make
from torchsim.kinematics import anchor_gap, dof_values, joint_frames, with_world
from torchsim.lanes import from_lanes

# ---------------------------------------------------------------------------------------------------- the hanging chain
LINKS = 4
LINK_LENGTH_M = 0.5
HORIZON_S = 0.5  # a map cell's run [s]
# 1 cm on 0.5 m links: ten times the 1 mm the accuracy tests allow for joint anchors (tests/test_mujoco_reference.py).
SEPARATION_BOUND_M = 0.01
OMEGA_SWING = 10.0  # [rad/s] initial angles shrink by OMEGA_SWING / omega on stiffer springs
_LOAD_DEFAULTS = inspect.signature(torchsim.load_mjcf).parameters
FLAG_BOUNDS = {k: _LOAD_DEFAULTS[k].default for k in ("max_speed", "max_distance")}
KAPPA_DEFAULT = torchsim.io_mjcf.JOINT_STIFFNESS


def chain_mjcf(h: float) -> str:
    """The hanging chain with MJCF timestep ``h`` [s]."""
    body = ""
    for i in reversed(range(LINKS)):
        body = (f'<body name="link{i}" pos="0 0 {-LINK_LENGTH_M if i else 0}"><joint type="hinge" axis="0 1 0"/>'
                f'<geom type="capsule" fromto="0 0 0 0 0 {-LINK_LENGTH_M}" size="0.03" mass="1" contype="0" '
                f'conaffinity="0"/>{body}</body>')
    return f'<mujoco><option timestep="{h}"/><worldbody>{body}</worldbody></mujoco>'


def chain_system(method: str, h: float, mass_ratio: torch.Tensor, omega: torch.Tensor, kappa: float = KAPPA_DEFAULT,
                 iterations: int = 1) -> torchsim.System:
    """Chain System for envs with link mass ratios ``mass_ratio (B,)`` and joint spring frequencies ``omega (B,)``
    [rad/s] (0: no spring); the divergence bounds are off (``studies/stability_map.py``'s docstring says why)."""
    sys = torchsim.load_mjcf(chain_mjcf(h), method=method, substeps=1, joint_stiffness=kappa,
                             xpbd_iterations=iterations, max_speed=math.inf, max_distance=math.inf)
    scale = torch.where(torch.arange(LINKS) % 2 == 1, mass_ratio[:, None], 1.0)
    sys = sys.replace(body_mass=sys.body_mass * scale, body_inertia=sys.body_inertia * scale[..., None, None])
    return sys.replace(dof_stiffness=omega[:, None] ** 2 / bare_dof_inverse_inertia(sys))


def bare_dof_inverse_inertia(sys: torchsim.System) -> torch.Tensor:
    """``(B or 1, D)`` inverse inertia of each dof on its two bare bodies at q0 (``rigid.dof_inverse_mass``): what an
    explicit joint torque accelerates in maximal coordinates before the joints couple the links."""
    bodies = with_world(*torchsim.kinematics.forward(sys, sys.q0[None], torch.zeros(1, sys.nv, dtype=sys.dtype)))
    inv = rigid.inverse_inertia(sys, bodies.x_quat, rigid.body_inverse_inertia(sys))
    return from_lanes(rigid.dof_inverse_mass(sys, inv, dof_values(sys, joint_frames(sys, bodies).axes)))


def initial_state(sys: torchsim.System, omega: torch.Tensor, gen: torch.Generator) -> torchsim.State:
    """Hinge angles U(-1, 1) rad, shrunk by ``OMEGA_SWING / omega`` where that is below 1, and rates N(0, 1) rad/s."""
    batch = omega.shape[0]
    swing = torch.clamp(OMEGA_SWING / omega, max=1.0)[:, None]
    q = swing * (2 * torch.rand(batch, sys.nq, generator=gen) - 1)
    return torchsim.init(sys, q, torch.randn(batch, sys.nv, generator=gen))


# ----------------------------------------------------------------------------------------------- an env at its defaults
def env_default_run(name: str, env_steps: int, batch: int = 2, seed: int = 0) -> dict:
    """Step env ``name`` at its defaults (model, method, substeps, float32, reset distribution, action mapping) for
    ``env_steps`` env steps of uniform random actions in [-1, 1] (one draw per env step, held over its frames), no
    resets. Returns whether any env diverged, whether the state is finite, and the largest joint anchor gap [m]
    over the batch at each env-step boundary: its median (a torn joint stays apart) and its peak (impacts spike)."""
    torch.manual_seed(seed)
    env = make(name, num_envs=batch)
    gaps = []
    for _ in range(env_steps):
        env.step(TensorDict(action=2 * torch.rand(batch, env.sys.nu, dtype=env.sys.dtype) - 1, batch_size=[batch]))
        gaps.append(anchor_gap(env.sys, env.state).max())
    state, gaps = env.state, torch.stack(gaps)
    return dict(diverged=bool(state.diverged.any()), finite=all(bool(t.isfinite().all()) for t in state[:6]),
                median_gap_m=float(gaps.median()), max_gap_m=float(gaps.max()))


def substeps_per_env_step(name: str) -> int:
    """Physics substeps in one env step of env ``name`` at its defaults (``frame_skip x substeps``)."""
    env = make(name)
    return env.frame_skip * env.sys.substeps


# ------------------------------------------------------------------------------------------------------------- the soak
MODES = ("random", "plus", "minus")
PROGRESS_EVERY = 100  # env steps between progress lines
ESTIMATE_AFTER = 20  # env steps timed (after the first, which builds the compiled step) before the estimate


class DivergenceWatch:
    """The env's stepper, recording the first divergence of every env: when the engine flags an env, the same
    physics step is run again from the same state with the divergence bounds off, to see which quantity broke.

    ``first`` holds, per env, the first divergence since the soak began as a dict (env step, step in its
    episode, quantity, body, value); ``env_step`` and ``episode_step`` are set by the soak loop before each env
    step."""

    def __init__(self, stepper: torchsim.Stepper):
        self.stepper = stepper
        self.sys = stepper.sys  # the env reads its System here
        self.unbounded = None  # the same step with the bounds off, built on the first divergence
        self.env_step, self.episode_step = 0, None
        self.first = {}

    def __call__(self, state: torchsim.State, ctrl: torch.Tensor) -> torchsim.State:
        new = self.stepper(state, ctrl)
        newly = new.diverged & ~state.diverged
        if newly.any():
            if self.unbounded is None:
                unbounded_sys = self.sys.replace(max_speed=math.inf, max_distance=math.inf)
                self.unbounded = torchsim.Stepper(unbounded_sys, self.stepper.strategy)
            unchecked = self.unbounded(state, ctrl)
            for env in newly.nonzero().flatten().tolist():
                self.first.setdefault(env, dict(env_step=self.env_step, episode_step=int(self.episode_step[env]),
                                                **self.what_broke(unchecked, env)))
        return new

    def what_broke(self, unchecked: torchsim.State, env: int) -> dict:
        """The quantity of env ``env``'s state ``unchecked`` (stepped with the bounds off) that fails the bounds,
        in ``contain_divergence``'s terms: non-finite (then frozen: ``diverged`` set), position, linear speed,
        angular speed."""
        if unchecked.diverged[env]:
            return dict(quantity="non-finite", body="-", value=math.nan)
        for quantity, values, bound in (("distance [m]", unchecked.x_pos, self.sys.max_distance),
                                        ("linear speed [m/s]", unchecked.xd_vel, self.sys.max_speed),
                                        ("angular speed [rad/s]", unchecked.xd_ang, self.sys.max_speed)):
            per_body = values[env].abs().amax(-1)
            if per_body.max() >= bound:
                body = int(per_body.argmax())
                return dict(quantity=quantity, body=self.sys.body_names[body], value=float(per_body[body]))
        return dict(quantity="not reproduced", body="-", value=math.nan)


def watched_env(name: str, num_envs: int, stepper: str = "auto"):
    """Env ``name`` at its defaults with ``num_envs`` envs, stepping through a :class:`DivergenceWatch`."""
    env = make(name, num_envs=num_envs, stepper=stepper)
    env.stepper = DivergenceWatch(env.stepper)
    return env


def constant_action(env, mode: str) -> torch.Tensor:
    """The action of ``mode``: the action spec's upper (``plus``) or lower (``minus``) bound for every env."""
    spec = env.action_spec
    return (spec.space.high if mode == "plus" else spec.space.low).expand(spec.shape).clone()


def soak(env, mode: str, steps: int, seed: int = 0) -> dict:
    """Step ``env`` ``steps`` times under action mode ``mode`` with resets; the diverged envs and the rate."""
    watch = env.stepper
    watch.first = {}
    torch.manual_seed(seed)
    td = env.reset()
    action = None if mode == "random" else constant_action(env, mode)
    ended = 0
    start = time.perf_counter()
    timed_from = None
    for t in range(steps):
        watch.env_step, watch.episode_step = t, env.step_count.clone()
        td["action"] = env.action_spec.rand() if action is None else action
        td = env.step(td)
        ended += int(td["next", "done"].sum())
        td = env.maybe_reset(step_mdp(td))
        if t == 0:
            timed_from = time.perf_counter()  # the first step builds (or loads) the compiled step
        if t > 0 and (t == ESTIMATE_AFTER or (t + 1) % PROGRESS_EVERY == 0 or t + 1 == steps):
            rate = t * env.batch_size[0] / max(time.perf_counter() - timed_from, 1e-9)
            print(f"  {type(env).__name__} {mode}: step {t + 1}/{steps}, {rate:,.0f} env-steps/s, diverged envs "
                  f"{len(watch.first)}, ETA {(steps - t - 1) * env.batch_size[0] / rate:.0f} s", flush=True)
    wall = time.perf_counter() - start
    rate = (steps - 1) * env.batch_size[0] / (time.perf_counter() - timed_from) if steps > 1 else math.nan
    return dict(diverged=len(watch.first), first=sorted(watch.first.items(), key=lambda e: e[1]["env_step"]),
                ended=ended, rate=rate, wall=wall)


def describe(first: list) -> str:
    """The earliest divergence of a run, for the table."""
    if not first:
        return "-"
    env, f = first[0]
    value = "" if math.isnan(f["value"]) else f" = {f['value']:.3g}"
    return (f"step {f['env_step']} (episode step {f['episode_step']}), env {env}: {f['quantity']} of "
            f"{f['body']}{value}")
