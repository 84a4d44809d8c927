"""Where generated step kernels are kept on disk, and the key that says when one can be reused.

A kernel's key is a digest of everything its code depends on (:func:`content_key`): the System's values, the
inputs' shapes and dtypes, the code generator's settings, the torch version and the source of every torchsim
module. Delete ``cache_dir()`` to clear the cache.
"""

import hashlib
import os
import pathlib

import torch

from torchsim import lanes

_PACKAGE = pathlib.Path(__file__).resolve().parents[2]  # torchsim/


def cache_dir() -> pathlib.Path:
    """``$TORCHSIM_CACHE_DIR``, else ``~/.cache/torchsim``."""
    return pathlib.Path(os.environ.get("TORCHSIM_CACHE_DIR") or pathlib.Path.home() / ".cache" / "torchsim")


def content_key(sys, args: list, options: dict, layout: tuple = ()) -> str:
    """A digest of everything generated code depends on: ``sys``'s values, the inputs' shapes (but not the batch
    size, which the code reads when it runs) and dtypes, the ``layout`` of what they pack, the generator's
    ``options``, the torch version and the source of every torchsim module."""
    digest = hashlib.sha256()
    for value in (torch.__version__, sorted(options.items()), layout,
                  [(tuple(x.shape[:-1]), lanes.per_env(x), str(x.dtype)) for x in args]):
        digest.update(repr(value).encode())
    for source in sorted(_PACKAGE.rglob("*.py")):
        digest.update(source.read_bytes())
    for x in sys.leaves():
        if isinstance(x, torch.Tensor):
            digest.update(repr((tuple(x.shape), str(x.dtype))).encode())
            digest.update(x.detach().cpu().numpy().tobytes())
        else:
            digest.update(repr(x).encode())
    return digest.hexdigest()[:32]
