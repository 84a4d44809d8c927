"""Checkpoints: reading (``weights_only``), writing (atomic, fsynced), which config keys a resumed run may change
(``RESUMABLE_KEYS``), the random streams and the policy they hold."""

import os
import pathlib
import pickle
import secrets

import torch
from omegaconf import DictConfig, OmegaConf
from torchrl.envs import TransformedEnv
from torchrl.modules import ProbabilisticActor

from torchsim.algos.env_factory import obs_norm
from torchsim.algos.networks import make_actor


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
