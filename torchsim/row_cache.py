"""Compiled row graphs on disk, so that a second process with the same model and batch size skips building them.

A row graph (``torchsim.rows``) is stored as a pickled ``GraphModule`` under ``cache_dir()/rows/<key>.pt``, its
key a digest of everything the graph depends on (:func:`content_key`). Inductor keeps the code it generates for the
graph in its own on-disk cache (``$TORCHINDUCTOR_CACHE_DIR``), keyed on the graph: a process that loads a stored
graph finds its compiled code there too. Delete ``cache_dir()`` to clear this cache.
"""

import hashlib
import os
import pathlib
import warnings

import torch
from torch.fx import GraphModule

from torchsim import lanes, progress


def cache_dir() -> pathlib.Path:
    """``$TORCHSIM_CACHE_DIR``, else ``~/.cache/torchsim``."""
    return pathlib.Path(os.environ.get("TORCHSIM_CACHE_DIR") or pathlib.Path.home() / ".cache" / "torchsim")


def content_key(sys, args: list, options: dict, layout: tuple = ()) -> str:
    """A digest of everything a compiled row graph depends on: ``sys``'s values, the inputs' shapes (but not the
    batch size, which the graph reads from its inputs) and dtypes, the ``layout`` of the leaves they pack, the
    inductor ``options``, the torch version and the source of every torchsim module."""
    digest = hashlib.sha256()
    for value in (torch.__version__, sorted(options.items()), layout,
                  [(tuple(x.shape[:-1]), lanes.per_env(x), str(x.dtype)) for x in args]):
        digest.update(repr(value).encode())
    for source in sorted(pathlib.Path(__file__).parent.rglob("*.py")):
        digest.update(source.read_bytes())
    for x in sys.leaves():
        if isinstance(x, torch.Tensor):
            digest.update(repr((tuple(x.shape), str(x.dtype))).encode())
            digest.update(x.detach().cpu().numpy().tobytes())
        else:
            digest.update(repr(x).encode())
    return digest.hexdigest()[:32]


def _path(key: str) -> pathlib.Path:
    return cache_dir() / "rows" / f"{key}.pt"


def load(key: str) -> GraphModule | None:
    """The graph stored under ``key``, or None (none stored, or unreadable: then it is rebuilt)."""
    path = _path(key)
    if not path.is_file():
        return None
    try:
        graph = torch.load(path, weights_only=False)
    except Exception as err:  # a truncated file, or one pickled by another version of torch
        warnings.warn(f"ignoring the cached row graph {path} ({type(err).__name__}: {err}); rebuilding it")
        return None
    progress.log.info("loaded the row graph from %s", path)
    return graph


def store(key: str, graph: GraphModule) -> GraphModule:
    """Store ``graph`` under ``key`` and return it as later processes will load it: inductor's cache key differs
    for a built and a loaded graph, so compiling the loaded one lets them find its code."""
    path = _path(key)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(graph, path.with_suffix(".tmp"))
    path.with_suffix(".tmp").replace(path)  # atomic: a concurrent reader sees the whole file or none
    return torch.load(path, weights_only=False)
