"""Where generated step kernels are kept on disk, and the key that says when one can be reused.

A kernel's key is a digest of everything its code depends on (:func:`content_key`): the System's values, the
inputs' shapes and dtypes, the code generator's settings (for C++: the compiler's version and the CPU's instruction
set, so machines that share a home directory never share a binary built for another CPU), the torch version and
the source of every torchsim module. Delete ``cache_dir()`` to clear the cache.

Every entry is written whole or not at all (a unique temporary name, then an atomic rename) with its SHA-256
beside it (``<entry>.sha256``), and checked against it before use: a truncated or altered entry is removed with one
warning and built again (:func:`verified`). Where the cache directory cannot be created or written, kernels are
built in a private temporary directory for the process, with one warning.
"""

import functools
import hashlib
import os
import pathlib
import tempfile
import threading
import warnings

import torch

from torchsim import lanes

_PACKAGE = pathlib.Path(__file__).resolve().parents[2]  # torchsim/


def cache_dir() -> pathlib.Path:
    """``$TORCHSIM_CACHE_DIR``, else ``~/.cache/torchsim``; a private temporary directory (with one warning) where
    that cannot be created or written."""
    return _writable(pathlib.Path(os.environ.get("TORCHSIM_CACHE_DIR") or pathlib.Path.home() / ".cache" / "torchsim"))


@functools.lru_cache(maxsize=None)
def _writable(root: pathlib.Path) -> pathlib.Path:
    try:
        root.mkdir(parents=True, exist_ok=True, mode=0o700)  # private: its binaries run in this user's processes
        with tempfile.TemporaryFile(dir=root):
            pass
        return root
    except OSError as err:
        fallback = pathlib.Path(tempfile.mkdtemp(prefix="torchsim-cache-"))
        warnings.warn(f"torchsim: the kernel cache {root} cannot be written ({err}); building kernels in {fallback} "
                      "for this process (set TORCHSIM_CACHE_DIR to a writable directory to keep them)", stacklevel=3)
        return fallback


def write(target: pathlib.Path, data: bytes) -> None:
    """Make ``data`` the entry ``target``, with its digest beside it; each file appears whole or not at all, so a
    concurrent process reads the old entry, the new one, or none (and a digest that does not match sends it to
    :func:`verified`'s rebuild, never to a half-written file)."""
    target.parent.mkdir(parents=True, exist_ok=True)
    _replace(_digest_path(target), hashlib.sha256(data).hexdigest().encode())
    _replace(target, data)


def verified(target: pathlib.Path) -> bool:
    """Whether the entry ``target`` exists and matches its recorded digest. One that does not (truncated, altered,
    or without a digest) is removed, with one warning, so that the caller builds it again."""
    if not target.is_file():
        return False
    try:
        intact = _digest_path(target).read_text().strip() == hashlib.sha256(target.read_bytes()).hexdigest()
    except FileNotFoundError:
        intact = False
    if not intact:
        warnings.warn(f"torchsim: the cached kernel {target} does not match its recorded digest (truncated or "
                      "altered); building it again", stacklevel=3)
        target.unlink(missing_ok=True)
        _digest_path(target).unlink(missing_ok=True)
    return intact


def _digest_path(target: pathlib.Path) -> pathlib.Path:
    return target.with_name(target.name + ".sha256")


def _replace(target: pathlib.Path, data: bytes) -> None:
    tmp = target.with_name(f"{target.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    tmp.write_bytes(data)
    tmp.replace(target)


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
