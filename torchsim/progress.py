"""Say what is being compiled, and for how long, while it compiles (minutes on CPU).

Messages go to the ``torchsim`` logger at INFO level (``torchsim.train`` shows them; elsewhere
``logging.basicConfig(level=logging.INFO)`` does).
"""

import contextlib
import logging
import sys
import threading
import types
import time

log = logging.getLogger("torchsim")

#: Seconds between "still compiling" lines.
HEARTBEAT_S = 15.0


@contextlib.contextmanager
def announce(what: str):
    """Log ``compiling <what>`` now, how long it has taken every ``HEARTBEAT_S`` seconds, and the total at the end."""
    t0 = time.perf_counter()
    done = threading.Event()

    def heartbeat():
        while not done.wait(HEARTBEAT_S):
            log.info("  ... compiling %s: %.0f s", what, time.perf_counter() - t0)

    log.info("compiling %s", what)
    thread = threading.Thread(target=heartbeat, daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join()
    log.info("compiled %s in %.1f s", what, time.perf_counter() - t0)


def announce_torch_compiles() -> None:
    """Announce every ``torch.compile`` compilation in this process (through dynamo's start and end callbacks),
    naming the function being compiled (and its module's class, for a method), and the backward pass that
    AOTAutograd compiles for it at the first ``backward()``. Registers the callbacks where they are not registered:
    ``torch._dynamo.reset()`` clears them, so call this again after a reset."""
    from torch._dynamo.callback import callback_handler

    if _on_compile_start not in callback_handler.start_callbacks:
        callback_handler.register_start_callback(_on_compile_start)
        callback_handler.register_end_callback(_on_compile_end)


def _on_compile_start(args) -> None:
    from torch._dynamo.callback import CallbackTrigger

    if args.callback_trigger == CallbackTrigger.LAZY_BACKWARD:
        what = f"the backward pass of {_compiled_names.get(args.compile_id, 'a compiled function')}"
    else:
        what = _compiled_names[args.compile_id] = _compiled_function_name()
    # compile ids read "frame/recompile": a recompile means new input shapes or types for a compiled function
    again = "" if str(args.compile_id).endswith("/0") else ", again for new inputs"
    _in_progress.enter_context(announce(f"{what} (torch.compile{again})"))


def _on_compile_end(args) -> None:
    _in_progress.close()


#: The announcement of the compilation in progress (dynamo compiles one frame at a time).
_in_progress = contextlib.ExitStack()
#: What each compile id compiled, to name its backward pass.
_compiled_names: dict[str, str] = {}


def _compiled_function_name() -> str:
    """The name of the function dynamo is compiling (its ``_compile(code, globals, locals, ...)`` frame is on the
    stack), as a method of the class of its ``self`` where it has one (a loss's ``forward`` is TorchRL's
    ``_forward_wrapper.<locals>.new_forward``, which says little alone: ``ClipPPOLoss.forward``)."""
    frame = sys._getframe()
    while frame is not None:
        code = frame.f_locals.get("code") if frame.f_code.co_name == "_compile" else None
        if isinstance(code, types.CodeType):
            owner = (frame.f_locals.get("locals") or {}).get("self")
            if owner is None or code.co_qualname.startswith(type(owner).__name__ + "."):
                return code.co_qualname
            return f"{type(owner).__name__}.{'forward' if code.co_name == 'new_forward' else code.co_name}"
        frame = frame.f_back
    return "a function"
