"""Reading a recipe's settings where a key has more than one source."""

from omegaconf import DictConfig


def compiles(cfg: DictConfig, part: str) -> bool:
    """Whether ``part`` (``"physics"``: the engine's compiled step; ``"loss"``: ``torch.compile`` of the loss) runs
    compiled: ``cfg.compile_<part>``, or where that is null or absent (checkpoints written before the split) the
    shorthand ``cfg.compile``."""
    value = cfg.get(f"compile_{part}")
    return bool(cfg.get("compile", True) if value is None else value)
