"""Pieces shared by the recipes: env construction, evaluation, and :class:`Run` (progress, logging, checkpoints,
budget, plots and the policy video of one training run); their networks are in ``torchsim.algos.networks``."""

import collections
import json
import logging
import os
import pathlib
import pickle
import secrets
import subprocess
import sys
import time
import warnings
from typing import NamedTuple

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDict
from torchrl.envs import Compose, ExplorationType, RewardSum, StepCounter, TransformedEnv, set_exploration_type
from torchrl.envs.transforms import RewardScaling
from torchrl.modules import ProbabilisticActor
from torchrl.record.loggers import get_logger

import torchsim.envs
from torchsim.algos import nav_policy
from torchsim.algos.distributed import Ranks
from torchsim.algos.networks import make_actor
from torchsim.algos.normalization import RunningNorm
from torchsim.envs.nav import video as nav_video
from torchsim.execution.mujoco import MujocoStepper

# tensordict reads a deprecated dynamo flag while torch.compile traces the loss (tensordict 0.14, torch 2.13)
warnings.filterwarnings("ignore", message=r"torch._dynamo.config.inline_inbuilt_nn_modules is deprecated")
log = logging.getLogger("torchsim.train")

class TrainingDiverged(RuntimeError):
    """A loss became non-finite; the message names the env step and the last good checkpoint."""


# ------------------------------------------------------------------------------------------------------ environment
def compiles(cfg: DictConfig, part: str) -> bool:
    """Whether ``part`` (``"physics"``: the engine's compiled step; ``"loss"``: ``torch.compile`` of the loss) runs
    compiled: ``cfg.compile_<part>``, or where that is null or absent (checkpoints written before the split) the
    shorthand ``cfg.compile``."""
    value = cfg.get(f"compile_{part}")
    return bool(cfg.get("compile", True) if value is None else value)


def make_env(cfg: DictConfig, num_envs: int, device, train: bool = False, like: TransformedEnv | None = None
             ) -> TransformedEnv:
    """The task batched over ``num_envs`` with running observation normalisation (``RunningNorm``, statistics over
    the batch too), episode return (``episode_reward``) and length (``step_count``); a ``train`` env also emits
    ``scaled_reward`` (``cfg.algo.reward_scale`` times the reward) and staggers its first episodes if
    ``cfg.stagger_episodes``, and compiles its step if ``cfg.capture``. The physics runs compiled (``torchsim.Stepper``,
    strategy ``auto``) if ``compiles(cfg, "physics")``,
    or in MuJoCo C if ``cfg.physics == "mujoco"`` (``torchsim.execution.mujoco``: the same task code on MuJoCo's
    physics); ``like``: an env whose stepper (System and compiled step) this one shares, for any ``num_envs`` above
    1. A navigation task (``torchsim.envs.NAV_ENVS``, no physics) has its depth normalised per pixel instead and
    draws its episodes from the layouts of ``cfg.env.split`` if ``train``, else of ``cfg.env.eval_split``, and, for a
    recurrent policy (``cfg.algo.policy_net.lstm``), holds its states (``nav_policy.recurrent_transforms``)."""
    physics = cfg.get("physics", "torchsim")  # checkpoints from before the key ran on torchsim
    contact_model = cfg.get("contact_model")
    method, substeps = cfg.get("method"), cfg.get("substeps")  # None: the task's (and in checkpoints before the keys)
    if physics not in ("torchsim", "mujoco"):
        raise ValueError(f"physics must be 'torchsim' or 'mujoco', got {physics!r}")
    if cfg.env.name in torchsim.envs.NAV_ENVS:
        base = torchsim.envs.make(cfg.env.name, num_envs=num_envs, device=device,
                                  episode_length=cfg.env.episode_length, num_layouts=cfg.env.num_layouts,
                                  split=cfg.env.split if train else cfg.env.eval_split, seed=cfg.seed)
        normalised = ["depth"]
        recurrent = nav_policy.recurrent_transforms(cfg.algo.policy_net)  # states, episode starts (or none)
    else:
        if like is not None:
            stepper = like.base_env.stepper
        elif physics == "mujoco":
            probe = torchsim.envs.make(cfg.env.name, device=device, contact_model=contact_model)  # System, MuJoCo model
            stepper = MujocoStepper(probe.base_sys, probe.mj_model)
        else:
            stepper = "auto" if compiles(cfg, "physics") else "eager"
        base = torchsim.envs.make(cfg.env.name, num_envs=num_envs, device=device,
                                  episode_length=cfg.env.episode_length,
                                  stagger_episodes=train and cfg.stagger_episodes, stepper=stepper,
                                  **(dict(contact_model=contact_model, method=method, substeps=substeps)
                                     if isinstance(stepper, str) else {}))
        if train and cfg.get("capture", False):
            if stepper != "auto":  # traced as a graph, the reference step compiles for minutes
                raise ValueError("capture=true compiles the env's step around the engine's compiled step: it needs "
                                 "compile=true (or compile_physics=true) and physics=torchsim")
            base.compile_step(mode="reduce-overhead" if torch.device(device).type == "cuda" else None)
        normalised = [k for k in ("observation", "privileged_state") if k in base.observation_spec.keys()]
        recurrent = []
    spec = base.observation_spec
    norm = RunningNorm({k: spec[k].shape[base.batch_dims:] for k in normalised}, decay=cfg.obs_norm_decay,
                       eps=1e-4, dtype=spec[normalised[0]].dtype).to(device)
    transforms = [norm, RewardSum(), StepCounter(), *recurrent]
    if train:  # the losses learn from scaled_reward; reward (and episode_reward) stay the task's
        transforms.append(RewardScaling(0.0, cfg.algo.reward_scale, in_keys=["reward"], out_keys=["scaled_reward"]))
    return TransformedEnv(base, Compose(*transforms))


def make_eval_env(cfg: DictConfig, train_env: TransformedEnv) -> TransformedEnv:
    """The evaluation env: ``cfg.eval.episodes`` envs sharing ``train_env``'s compiled step. On CPU that step serves
    any batch above one env; on a GPU it is compiled for its batch (the ``loop`` strategy, static shapes), so there
    the evaluation runs on the training batch's size instead of compiling a second graph (measured on an H100: a
    second 43 s compile for 128 envs, none for the training batch)."""
    episodes = cfg.eval.episodes
    if train_env.device.type != "cpu" and compiles(cfg, "physics") and episodes != train_env.batch_size[0]:
        episodes = train_env.batch_size[0]
        log.info(f"evaluating {episodes} episodes (the training batch) on {train_env.device}: the compiled step "
                 f"serves one batch size there")
    if nav_policy.is_nav_env(train_env):
        return make_env(cfg, episodes, train_env.device)
    return make_env(cfg, episodes, train_env.device, like=train_env)


def obs_norm(env: TransformedEnv) -> RunningNorm:
    return env.transform[0]


# ------------------------------------------------------------------------------------------------------- evaluation
class Evaluation(NamedTuple):
    """Per env (B,): the return and length of its first episode, and, for goal-reaching tasks, the goal distance
    [m] at the episode's end (else None); ``trajectory``: env 0's episode when recorded (else None), as ``q``
    rows ``(T, nq)`` for physics envs and :class:`~torchsim.envs.nav.video.NavFrame` s for navigation envs; for
    navigation tasks (which emit them), the episode's ``success`` (bool) and ``spl``."""

    ret: torch.Tensor
    length: torch.Tensor
    final_distance: torch.Tensor | None
    trajectory: np.ndarray | list | None
    success: torch.Tensor | None = None
    spl: torch.Tensor | None = None

    def success_rate(self, success_distance: float) -> float:
        return (self.final_distance < success_distance).float().mean().item()


@torch.no_grad()
def evaluate(env: TransformedEnv, policy, max_steps: int, record: bool = False, seed: int | None = None,
             deterministic: bool = True) -> Evaluation:
    """Deterministic evaluation (or, not ``deterministic``, with sampled actions) of each env's first episode (at
    most ``max_steps`` steps); with ``record``, env 0's trajectory for a video (``video``). Finished envs keep stepping,
    masked out, so the batch stays fixed; the loop stops once every env has finished. With ``seed``, the episodes
    start from the same states at every call (drawn from a forked RNG, leaving the caller's stream alone), so
    successive evaluations compare policies, not start draws; a navigation env draws its episodes from its own
    generator, which ``seed`` then reseeds."""
    nav = nav_policy.is_nav_env(env)
    if seed is None:
        td = env.reset()
    else:
        with torch.random.fork_rng(devices=[env.device] if env.device.type == "cuda" else []):
            torch.manual_seed(seed)
            if nav:
                env.set_seed(seed)
            td = env.reset()
    alive = torch.ones(env.batch_size, dtype=torch.bool, device=env.device)
    ret = torch.zeros(env.batch_size, device=env.device)
    length = torch.zeros(env.batch_size, dtype=torch.long, device=env.device)
    goal_task = "goal_distance" in env.observation_spec.keys()
    distance = torch.full(env.batch_size, float("nan"), device=env.device) if goal_task else None
    success = torch.zeros(env.batch_size, dtype=torch.bool, device=env.device) if nav else None
    spl = torch.zeros(env.batch_size, device=env.device) if nav else None
    snapshot = (lambda: nav_video.snapshot(env.base_env, 0)) if nav else (lambda: env.base_env.state.q[0].cpu())
    trajectory = [snapshot()] if record else None
    with set_exploration_type(ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM):
        for t in range(max_steps):
            td = env.step(policy(td))
            ret += td["next", "reward"].squeeze(-1) * alive
            length += alive
            if goal_task:
                distance = torch.where(alive, td["next", "goal_distance"].squeeze(-1), distance)
            if nav:  # nonzero on an episode's last step only
                success |= td["next", "success"].squeeze(-1) & alive
                spl += td["next", "spl"].squeeze(-1) * alive
            if record and bool(alive[0]):
                trajectory.append(snapshot())
            alive &= ~td["next", "done"].squeeze(-1)
            if t % 10 == 9 and not alive.any():  # one host sync every 10 steps
                break
            td = env.step_mdp(td)
    if record and not nav:
        trajectory = torch.stack(trajectory).double().numpy()
    return Evaluation(ret, length, distance, trajectory, success, spl)


def load_checkpoint(path, device="cpu") -> dict:
    """The checkpoint ``path`` (a ``last.pt``) with its tensors on ``device``, read with ``weights_only``: tensors and
    plain containers only, so a hostile file cannot run code as it loads (a checkpoint holds nothing else:
    ``Run.save``)."""
    try:
        return torch.load(path, map_location=device, weights_only=True)
    except pickle.UnpicklingError as err:
        raise pickle.UnpicklingError(f"refused to load {path}: it holds objects other than tensors and plain "
                                     f"containers, which a torchsim checkpoint never does ({err})") from err


def restore_rng(ckpt: dict, device: torch.device) -> None:
    """Continue the random streams of checkpoint ``ckpt``: the CPU generator's saved state goes back to the CPU
    generator and, for a run on a GPU, the GPU's to ``device``'s. Both states are CPU ByteTensors, as the setters
    require, whatever device the checkpoint's tensors were loaded onto."""
    torch.set_rng_state(ckpt["rng"].cpu())
    if device.type == "cuda" and "cuda_rng" in ckpt:  # none where the checkpointed run ran on the CPU
        torch.cuda.set_rng_state(ckpt["cuda_rng"].cpu(), device)


#: The config keys a resumed run may set anew: how long it runs (``budget``), how it is watched (evaluation, progress
#: lines, checkpoints, logger, video) and where and how fast it computes (device, threads, compile). The others
#: define what is learned (algorithm and hyperparameters, networks, env, physics, seed) and must match the
#: checkpoint's: changing one makes a new run, not a continued one.
RESUMABLE_KEYS = ("budget", "eval", "print_every", "checkpoint_every", "recent_episodes", "logger", "video", "device",
                  "threads", "compile", "compile_physics", "compile_loss", "capture", "resume")


def check_resumable(ckpt: dict, cfg: DictConfig, world_size: int, path) -> None:
    """Refuse (ValueError naming each key and both values) to resume checkpoint ``ckpt`` (read from ``path``) with
    ``cfg`` on ``world_size`` ranks where its config differs outside ``RESUMABLE_KEYS`` or its world size differs
    (each rank's share of the envs, and their streams, would change)."""
    changes = config_changes(ckpt["cfg"], cfg)
    saved_world_size = ckpt.get("world_size")  # None: written before checkpoints recorded it
    if saved_world_size is not None and saved_world_size != world_size:
        changes.append(f"world size ({saved_world_size} ranks in the checkpoint, {world_size} now)")
    if changes:
        raise ValueError(f"cannot resume {path}: this run differs from the checkpoint's in {'; '.join(changes)}. A "
                         f"resumed run may change only {', '.join(RESUMABLE_KEYS)}: start a new run to change others")


def config_changes(saved: dict, cfg: DictConfig) -> list[str]:
    """The keys outside ``RESUMABLE_KEYS`` whose values differ between a checkpoint's config ``saved`` and ``cfg``,
    each with both values. A key that only one of them has (added to the configs after the checkpoint was written,
    or removed since) has no value to compare with and is left out."""
    old, new = _flatten(saved), _flatten(OmegaConf.to_container(cfg, resolve=True))
    return [f"{key} ({old[key]!r} in the checkpoint, {new[key]!r} now)" for key in old
            if key in new and old[key] != new[key] and key.split(".")[0] not in RESUMABLE_KEYS]


def _flatten(tree: dict, prefix: str = "") -> dict:
    """``tree``'s leaves by dotted key: ``{"algo": {"lr": 1e-3}}`` -> ``{"algo.lr": 1e-3}`` (a list is a leaf)."""
    flat = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            flat.update(_flatten(value, f"{prefix}{key}."))
        else:
            flat[prefix + str(key)] = value
    return flat


def save_checkpoint(ckpt: dict, path: pathlib.Path, previous: pathlib.Path) -> None:
    """Write ``ckpt`` to ``path``, moving the file that was there to ``previous``. It is written under a unique temp
    name beside ``path`` (two writers never share one), flushed and fsynced, and only then renamed, so neither
    name ever holds part of a checkpoint, whatever stops the process; a failed write leaves no temp file behind."""
    # not mkstemp: its files are private to the user (0600), a checkpoint gets the permissions the umask gives
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
    f = open(tmp, "xb")  # x: fails rather than share a name (the cleanup below is then not ours to do)
    try:
        with f:
            torch.save(ckpt, f)
            f.flush()
            os.fsync(f.fileno())
        if path.exists():  # a process stopped between these renames leaves previous (the last good state)
            os.replace(path, previous)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    directory = os.open(path.parent, os.O_RDONLY)  # the renames reach the disk too, not only the data
    try:
        os.fsync(directory)
    finally:
        os.close(directory)


def load_policy(ckpt: dict, env: TransformedEnv, device) -> ProbabilisticActor:
    """The actor of checkpoint ``ckpt`` (a loaded ``last.pt``), with ``env``'s normaliser set to the checkpoint's
    statistics and frozen."""
    cfg = OmegaConf.create(ckpt["cfg"])
    actor = make_actor(env, cfg.algo.policy_net, device)
    actor.load_state_dict(ckpt["actor"])
    obs_norm(env).load_state_dict(ckpt["state"]["obs_norm"])
    obs_norm(env).freeze()
    return actor


def video(env: TransformedEnv, env_name: str, trajectory, path: pathlib.Path) -> None:
    """Write env 0's recorded ``trajectory`` (``evaluate(..., record=True)``) as the GIF ``path``: a navigation
    env's map and depth view (``torchsim.envs.nav.video``, 10 frames/s), a physics env's bodies (``render_gif``)."""
    if nav_policy.is_nav_env(env):
        from torchsim.envs.video import save_gif

        save_gif(nav_video.episode_frames(trajectory), path, fps=10)
        log.info(f"video: {path}")
    else:
        render_gif(env_name, trajectory, env.base_env.dt, path)


def render_gif(env_name: str, qpos: np.ndarray, dt: float, path: pathlib.Path, renderer: str = "torchsim",
               width: int = 320, height: int = 240) -> None:
    """Write a ``width`` x ``height`` GIF of ``qpos``. ``renderer="torchsim"`` (default): torchsim's own renderer,
    in this process (no GL context; ``torchsim.envs.video.render_frames_torchsim``); models it cannot draw (height
    fields) fall back to ``"mujoco"``: MuJoCo's renderer in a child process, as MuJoCo picks its GL backend when first
    imported (``MUJOCO_GL``), which in this process happened before we could choose EGL."""
    path = pathlib.Path(path)
    if renderer == "torchsim":
        from torchsim.envs.video import render_frames_torchsim, save_gif
        from torchsim.render import UnsupportedGeomError

        task = torchsim.envs.make(env_name)
        try:
            save_gif(render_frames_torchsim(task.mj_model, task.sys, qpos, width, height), path, fps=1.0 / dt)
            log.info(f"video: {path}")
            return
        except UnsupportedGeomError as err:
            log.info(f"torchsim's renderer cannot draw {env_name} ({err}); rendering with MuJoCo")
    np.save(path.with_suffix(".npy"), qpos)
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    proc = subprocess.run([sys.executable, "-m", "torchsim.algos.render", env_name, str(path.with_suffix(".npy")),
                           str(path), str(1.0 / dt), str(width), str(height)], env=env, capture_output=True, text=True)
    if proc.returncode:
        warnings.warn(f"no video ({proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else 'render failed'})")
    else:
        log.info(f"video: {path}")


# ------------------------------------------------------------------------------------------------------- a training run
#: ``Run.state`` entries of what a rank's random streams have drawn ahead: the training envs' running episodes
#: (``RunningEpisodes``, APG's ``Rollout``) and PPO's next minibatch order (its sampler draws it as the last runs
#: out). Each rank has its own: only rank 0's are saved, and on resume the other ranks, on streams of their own,
#: start new ones, as rank 0 does from a checkpoint written before these were saved or on another kind of device
#: (whose generators' states do not fit this one's).
EPISODES, MINIBATCH_ORDER = "episodes", "minibatch_order"


class RunningEpisodes:
    """The running episodes of a collector's ``env`` as a ``state_dict``: the collector's carried step (the policy's
    next input, with the episodes' returns and step counts and a recurrent policy's states, which TorchRL 0.14 keeps
    in ``Collector._carrier``) and the env's own state (``episode_state``). A resumed run restores them to continue
    those episodes as the uninterrupted run would: starting new ones draws other random numbers, and the runs
    part."""

    def __init__(self, collector, env: TransformedEnv):
        self.collector, self.env = collector, env

    def state_dict(self) -> dict:
        return {"carrier": self.collector._carrier.to_dict(), "env": self.env.base_env.episode_state()}

    def load_state_dict(self, state: dict) -> None:
        carrier = self.collector._carrier
        self.collector._carrier = TensorDict(state["carrier"], batch_size=carrier.batch_size, device=carrier.device)
        self.env.base_env.load_episode_state(state["env"])


class Run:
    """Bookkeeping of one training run in ``out_dir``: env-step budget and wall clock, progress lines, TorchRL logger,
    periodic deterministic evaluation, checkpoints (``checkpoints/last.pt``, written only after a finite update, so
    it is always the last good state, and ``checkpoints/previous.pt``, the one before), resume, and the final plot
    and video.

    ``state`` maps names to everything with a ``state_dict`` that a resumed run needs (networks, loss module with
    its target networks and temperature, optimisers, learning-rate schedule, observation normaliser, and what the
    random stream has drawn ahead: ``EPISODES``, ``MINIBATCH_ORDER``), loaded in its order. With several ``ranks``
    only rank 0 logs, evaluates (the others pass no ``eval_env``), checkpoints and plots; env steps count every
    rank's.

    A resumed run (``cfg.resume``, ``load``) continues the checkpointed one as if it had not stopped: same state,
    episodes, random streams (rank 0's) and counters, so with the same budget it trains as the uninterrupted run
    would. Its history and wall clock (logs, plots) continue the checkpoint's; ``budget.minutes``, though, counts
    this session's time only, from its start: a resumed run gets the minutes it is given, whatever the run before
    it took. A budget the checkpoint has already reached is refused, as is a config that changes what is learned
    (``RESUMABLE_KEYS``).
    """

    def __init__(self, cfg: DictConfig, out_dir, state: dict, actor, eval_env: TransformedEnv | None, train_env,
                 ranks: Ranks = Ranks()):
        self.cfg, self.out_dir, self.state, self.actor = cfg, pathlib.Path(out_dir), state, actor
        self.eval_env, self.train_env, self.ranks = eval_env, train_env, ranks
        self.device = ranks.device(cfg.device)
        self.logger = get_logger(cfg.logger, logger_name=str(self.out_dir), experiment_name="logs") \
            if ranks.is_main else None
        self.env_steps, self.iteration, self.elapsed = 0, 0, 0.0
        # rows (env_steps, wall_s, value); step_reward: the mean reward per env step of each iteration's batch
        self.history = {"train": [], "eval": [], "eval_success": [], "step_reward": []}
        self.recent = collections.deque(maxlen=cfg.recent_episodes)
        self.recent_success = collections.deque(maxlen=cfg.recent_episodes)  # navigation: STOPs within reach
        self.next_eval = 0 if cfg.eval.at_start else cfg.eval.interval_steps
        self.saved_iteration = None  # the iteration last.pt holds, once this run wrote it
        self.iteration_s = self.eval_s = 0.0  # the last iteration's and evaluation's wall-clock seconds
        self.session_t0 = time.perf_counter()  # budget.minutes counts from here
        if cfg.resume:
            self.load(cfg.resume)
        self.t0 = self.session_t0 - self.elapsed  # the wall clock counts the sessions before this one too
        self.t_last, self.steps_last = time.perf_counter(), self.env_steps
        self.unprinted_s, self.unprinted_steps = 0.0, 0  # training time and env steps since the last progress line
        self.t_collected, self.unprinted_collect_s = self.t_last, 0.0  # when the batch arrived; collecting time

    # -- budget
    @property
    def wall(self) -> float:
        return time.perf_counter() - self.t0

    def finished(self) -> bool:
        return self.spent_budget() is not None

    def spent_budget(self) -> str | None:
        """The budget that is spent, with what was reached, or None: env steps, an eval return reached, or this
        session's wall-clock minutes, where the run also stops early enough that its final evaluation (timed as the
        last one) ends within the budget."""
        b = self.cfg.budget
        session_s = time.perf_counter() - self.session_t0
        if b.env_steps is not None and self.env_steps >= b.env_steps:
            return f"budget.env_steps={b.env_steps} (env step {self.env_steps})"
        if b.minutes is not None and session_s + self.iteration_s + self.eval_s >= 60 * b.minutes:
            return f"budget.minutes={b.minutes}"
        if b.eval_return is not None and self.history["eval"] and self.history["eval"][-1][2] >= b.eval_return:
            return f"budget.eval_return={b.eval_return} (eval return {self.history['eval'][-1][2]:.2f})"
        return None

    # -- per iteration
    def record_batch(self, data) -> None:
        """Count the batch's env steps and collect the returns (and, for navigation, the successes) of the
        episodes that ended in it."""
        self.t_collected = time.perf_counter()  # the iteration's collecting ends here, its learning begins
        self.env_steps += data.numel() * self.ranks.world_size
        done = data["next", "done"].squeeze(-1)
        returns = data["next", "episode_reward"].squeeze(-1)[done]
        self.recent.extend(returns.tolist())
        if "success" in data["next"].keys():
            self.recent_success.extend(data["next", "success"].squeeze(-1)[done].tolist())
        self.step_reward = data["next", "reward"].mean().item()

    def check_update(self, losses, grad_norm: torch.Tensor, minibatch) -> None:
        """Before each optimiser step: stop if a loss term or the gradient norm is non-finite.

        Checking every minibatch (not just the iteration's last) stops before a bad step reaches the weights, so
        the networks and the last checkpoint stay good; the offending minibatch is saved for diagnosis."""
        values = {**{k: v.detach() for k, v in losses.items() if v.numel() == 1}, "grad_norm": grad_norm}
        finite = torch.isfinite(torch.stack([v.reshape(()).float() for v in values.values()]))
        if bool(finite.all()):
            return
        bad = [k for k, ok in zip(values, finite.tolist()) if not ok]
        saved = self.out_dir / self.diverged_file_name()
        saved.parent.mkdir(parents=True, exist_ok=True)
        torch.save(minibatch.detach().cpu(), saved)
        ckpt = self.out_dir / "checkpoints" / "last.pt"
        raise TrainingDiverged(f"non-finite {', '.join(bad)} at env step {self.env_steps} (iteration "
                               f"{self.iteration + 1}); minibatch saved to {saved}; last good checkpoint: "
                               f"{ckpt if ckpt.exists() else 'none'}")

    def diverged_file_name(self) -> str:
        """Where a diverged minibatch goes in ``out_dir``: every rank stops on the same non-finite step, and ranks
        above 0 share the system's temp dir as their ``out_dir`` (``torchsim.algos.train``), with other runs too,
        so their files carry the rank and the process id."""
        if self.ranks.is_main:
            return "diverged_minibatch.pt"
        return f"diverged_minibatch_rank{self.ranks.rank}_pid{os.getpid()}.pt"

    def end_iteration(self, losses: dict) -> None:
        """After an update: log; print a progress line every ``cfg.print_every`` iterations (with the env-steps/s
        of the iterations since the last one) and with every evaluation; evaluate and checkpoint when due."""
        self.iteration += 1
        if not self.ranks.is_main:
            return
        self.iteration_s = time.perf_counter() - self.t_last
        steps = self.env_steps - self.steps_last
        self.unprinted_s, self.unprinted_steps = self.unprinted_s + self.iteration_s, self.unprinted_steps + steps
        self.unprinted_collect_s += self.t_collected - self.t_last
        self.steps_last = self.env_steps
        recent = float(np.mean(self.recent)) if self.recent else float("nan")
        metrics = {**{f"train/{k}": float(v) for k, v in losses.items()}, "train/step_reward": self.step_reward,
                   "time/env_steps_per_s": steps / max(self.iteration_s, 1e-9), "time/wall_s": self.wall}
        if self.recent:
            metrics["train/return"] = recent
            self.history["train"].append((self.env_steps, self.wall, recent))
        success = ""
        if self.recent_success:
            metrics["train/success_rate"] = rate = float(np.mean(self.recent_success))
            success = f"  success {rate:4.0%}"
        self.history["step_reward"].append((self.env_steps, self.wall, self.step_reward))
        self.log(metrics)
        line = (f"[{self.cfg.algo.name} {self.cfg.env.name}] it {self.iteration:4d}  steps {self.env_steps:>11,d}  "
                f"{self.unprinted_steps / max(self.unprinted_s, 1e-9):7.0f} steps/s "
                f"(collect {self.unprinted_collect_s / max(self.unprinted_s, 1e-9):3.0%})  return {recent:8.2f}  "
                f"reward/step {self.step_reward:7.3f}{success}  {self.wall / 60:5.1f} min")
        eval_due = self.env_steps >= self.next_eval or self.finished()
        if eval_due:
            line += self.evaluate() + f" ({self.eval_s:.0f} s)"
            self.next_eval = self.env_steps + self.cfg.eval.interval_steps
        if eval_due or self.iteration % self.cfg.print_every == 0:
            log.info(line)
            self.unprinted_s = self.unprinted_steps = self.unprinted_collect_s = 0
        if self.iteration % self.cfg.checkpoint_every == 0 or self.finished():
            self.save()
        self.t_last = time.perf_counter()  # the next iteration's time and rate leave evaluation and saving out

    def log(self, metrics: dict) -> None:
        if self.logger is not None:
            for k, v in metrics.items():
                self.logger.log_scalar(k, v, step=self.env_steps)

    def evaluate(self) -> str:
        """Evaluate, record and log; return the progress-line text (return, and success for goal tasks)."""
        self.sync_eval_norm()
        start = time.perf_counter()
        result = evaluate(self.eval_env, self.actor, self.cfg.eval.max_steps, seed=self.eval_seed())
        self.eval_s = time.perf_counter() - start
        mean = result.ret.mean().item()
        self.history["eval"].append((self.env_steps, self.wall, mean))
        metrics = {"eval/return": mean, "eval/episode_length": result.length.float().mean().item()}
        text = f"  eval {mean:8.2f}"
        if result.final_distance is not None:
            success = result.success_rate(self.eval_env.base_env.success_distance)
            self.history["eval_success"].append((self.env_steps, self.wall, success))
            metrics.update({"eval/success_rate": success,
                            "eval/final_distance": result.final_distance.mean().item()})
            text += f" (success {success:.0%}, final distance {result.final_distance.median().item():.3f} m)"
        if result.spl is not None:
            success, spl = result.success.float().mean().item(), result.spl.mean().item()
            self.history["eval_success"].append((self.env_steps, self.wall, success))
            self.history.setdefault("eval_spl", []).append((self.env_steps, self.wall, spl))
            metrics.update({"eval/success_rate": success, "eval/spl": spl})
            text += f" (success {success:.0%}, SPL {spl:.3f}, length {result.length.float().mean().item():.0f})"
        self.log(metrics)
        return text

    def eval_seed(self) -> int:
        """``eval.seed``, or where it is null one of each evaluation's own, from the run's seed and env step: fresh
        start states at every evaluation, drawn from a stream of their own, not the training's, so that an
        evaluation (as the one a run makes where its budget ends) leaves the training as it would have been without
        it."""
        if self.cfg.eval.seed is not None:
            return self.cfg.eval.seed
        return int(np.random.SeedSequence([self.cfg.seed, self.env_steps]).generate_state(1)[0])

    def sync_eval_norm(self) -> None:
        """Evaluate with the training normaliser's current statistics, frozen."""
        norm = obs_norm(self.eval_env)
        norm.load_state_dict(obs_norm(self.train_env).state_dict())
        norm.freeze()

    # -- checkpoints
    def save(self) -> pathlib.Path:
        """Write ``checkpoints/last.pt`` (rank 0), the one before it kept as ``checkpoints/previous.pt``: tensors and
        plain containers only, so that it loads with ``weights_only`` (``load_checkpoint``)."""
        path = self.out_dir / "checkpoints" / "last.pt"
        if not self.ranks.is_main:
            return path
        path.parent.mkdir(parents=True, exist_ok=True)
        ckpt = {"cfg": OmegaConf.to_container(self.cfg, resolve=True), "world_size": self.ranks.world_size,
                "state": {k: v.state_dict() for k, v in self.state.items()},
                "actor": self.actor.state_dict(),
                "counters": {"env_steps": self.env_steps, "iteration": self.iteration, "elapsed": self.wall,
                             "next_eval": self.next_eval},
                "recent": {"returns": list(self.recent), "successes": list(self.recent_success)},
                "history": self.history, "rng": torch.get_rng_state()}
        if self.device.type == "cuda":  # the envs' and the policy's draws on the GPU
            ckpt["cuda_rng"] = torch.cuda.get_rng_state(self.device)
        save_checkpoint(ckpt, path, path.with_name("previous.pt"))
        self.saved_iteration = self.iteration
        return path

    def load(self, path) -> None:
        """Continue the run checkpointed at ``path`` (see the class): its tensors load onto this rank's device; rank 0
        continues the checkpoint's random streams and what they drew ahead (``EPISODES``), the other ranks, whose
        streams the checkpoint does not hold, start streams of their own. Refused (ValueError) where the config
        changes what is learned (``check_resumable``) or a budget is already spent."""
        ckpt = load_checkpoint(path, self.device)
        check_resumable(ckpt, self.cfg, self.ranks.world_size, path)
        same_streams = self.ranks.is_main and torch.device(ckpt["cfg"]["device"]).type == self.device.type
        for name, part in self.state.items():
            if name in (EPISODES, MINIBATCH_ORDER) and not (same_streams and name in ckpt["state"]):
                continue  # not this rank's streams, or not saved: drawn anew (EPISODES)
            part.load_state_dict(ckpt["state"][name])
        c = ckpt["counters"]
        self.env_steps, self.iteration, self.elapsed, self.next_eval = (c["env_steps"], c["iteration"], c["elapsed"],
                                                                      c["next_eval"])
        self.history.update(ckpt["history"])
        recent = ckpt.get("recent", {"returns": [], "successes": []})  # absent from checkpoints before it was saved
        self.recent.extend(recent["returns"])
        self.recent_success.extend(recent["successes"])
        if self.ranks.is_main:
            restore_rng(ckpt, self.device)
        else:  # rank 0's stream would make this rank's envs repeat rank 0's
            torch.manual_seed(self.cfg.seed + self.ranks.rank + self.ranks.world_size * self.iteration)
        spent = self.spent_budget()
        if spent is not None:
            raise ValueError(f"cannot resume {path}: its run has already reached {spent}; raise that budget, or set "
                             f"it to null, to train on")
        log.info(f"resumed from {path} at env step {self.env_steps}")

    # -- end of run
    def finish(self) -> None:
        """Save the final checkpoint, plot the curves, render the policy and write ``summary.json`` (rank 0)."""
        if not self.ranks.is_main:
            return
        if self.saved_iteration != self.iteration:  # else last.pt has this state and previous.pt the one before
            self.save()
        plot_curves(self.history, self.out_dir / "curves.png", f"{self.cfg.algo.name} {self.cfg.env.name}")
        if self.cfg.video.enabled:
            self.sync_eval_norm()
            trajectory = evaluate(self.eval_env, self.actor, self.cfg.video.steps, record=True).trajectory
            video(self.eval_env, self.cfg.env.name, trajectory, self.out_dir / "policy.gif")
        self.summary = summary = {"env_steps": self.env_steps, "wall_s": round(self.wall, 1),
                   "env_steps_per_s": round(self.env_steps / max(self.wall, 1e-9), 1),
                   "final_eval_return": self.history["eval"][-1][2] if self.history["eval"] else None}
        if self.history["eval_success"]:
            summary["final_eval_success_rate"] = self.history["eval_success"][-1][2]
        (self.out_dir / "summary.json").write_text(json.dumps(summary, indent=1))
        log.info(f"done: {summary}; outputs in {self.out_dir}")


def plot_curves(history: dict, path, title: str) -> None:
    """Eval and train return against env steps and against wall-clock minutes, and the training batches' mean reward
    per env step (it moves before whole-episode returns do in short runs); for goal-reaching tasks a fourth panel
    shows the evaluation success rate against env steps (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    goal_task = bool(history.get("eval_success"))
    fig, axes = plt.subplots(1, 4 if goal_task else 3, figsize=(20 if goal_task else 15, 3.8))
    for key, style in (("eval", "o-"), ("train", "-")):
        rows = np.array(history[key]).reshape(-1, 3)
        axes[0].plot(rows[:, 0], rows[:, 2], style, label=f"{key} return")
        axes[1].plot(rows[:, 1] / 60, rows[:, 2], style, label=f"{key} return")
    for ax in axes[:2]:
        ax.set_ylabel("return")
    rows = np.array(history.get("step_reward", [])).reshape(-1, 3)
    axes[2].plot(rows[:, 0], rows[:, 2], "-", color="C2", label="train reward per env step")
    axes[2].set_ylabel("reward per step")
    if goal_task:
        rows = np.array(history["eval_success"])
        axes[3].plot(rows[:, 0], rows[:, 2], "o-", label="eval success rate")
        axes[3].set_ylabel("success rate")
        axes[3].set_ylim(-0.02, 1.02)
    for ax in axes:
        ax.set_xlabel("wall-clock (min)" if ax is axes[1] else "env steps")
        ax.grid(alpha=0.3)
        ax.legend()
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def maybe_compile(loss_module, cfg: DictConfig):
    """``torch.compile`` the loss when ``compiles(cfg, "loss")``. Graph breaks (TorchRL's losses have some) run as Python
    between compiled pieces; a compiler error is raised, never hidden behind a silently slow eager loss."""
    return torch.compile(loss_module) if compiles(cfg, "loss") else loss_module
