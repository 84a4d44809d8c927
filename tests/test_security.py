"""Trust under hostile input: checkpoints load with ``weights_only`` (a pickle that would run code is refused by every
load path, before its code runs), and the browser viewer serves this machine only unless told otherwise."""

import ast
import importlib.util
import os
import pathlib
import pickle
import socket
import sys
import warnings

import pytest
import torch

from torchsim.algos import evaluate as evaluate_cli
from torchsim.algos.checkpoints import load_checkpoint
from torchsim.algos.train import run
from tiny_runs import tiny_ppo

REPO = pathlib.Path(__file__).resolve().parent.parent


def script(where: str, monkeypatch):
    """The module ``<where>.py``, e.g. ``scripts/view`` (its folder on the path for its own imports): the scripts,
    benchmarks and studies that read checkpoints are the subjects here, run as their users run them."""
    folder, name = where.split("/")
    monkeypatch.syspath_prepend(str(REPO / folder))
    monkeypatch.setenv("MUJOCO_GL", os.environ.get("MUJOCO_GL", "egl"))  # record_video sets it on import
    spec = importlib.util.spec_from_file_location(f"script_{name}", REPO / folder / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class Payload:
    """Unpickling this calls ``Path.touch(marker)``: the marker file appears where a loader ran the pickle's code."""

    def __init__(self, marker: pathlib.Path):
        self.marker = marker

    def __reduce__(self):
        return pathlib.Path.touch, (self.marker,)


@pytest.fixture
def hostile(tmp_path):
    """``(checkpoint, marker)``: a file shaped like a checkpoint whose config unpickles by creating ``marker``."""
    path, marker = tmp_path / "last.pt", tmp_path / "pwned"
    torch.save({"cfg": Payload(marker), "state": {}, "actor": {}, "counters": {}, "history": {}}, path)
    return path, marker


def test_the_payload_runs_code_when_loaded_freely(hostile):
    """The fixture is a real attack: a full unpickler creates the marker (so its absence below means refusal)."""
    path, marker = hostile
    torch.load(path, weights_only=False)  # what every loader did before: the one call left in the repo, on purpose
    assert marker.exists()


# every path by which torchsim reads a checkpoint: the library, resume, the evaluation CLI, the scripts and studies
LOADERS = {
    "load_checkpoint": lambda path, mp: load_checkpoint(path),
    "resume": lambda path, mp: run(tiny_ppo(f"resume={path}"), path.parent / "resumed"),
    "torchsim.evaluate": lambda path, mp: evaluate_cli.main([f"checkpoint={path}"]),
    "view.py --policy/--watch": lambda path, mp: script("scripts/view", mp).load(path),
    "record_video.py --policy": lambda path, mp: script("scripts/record_video", mp).policy_rollout(str(path), 5),
    "pusher_outcome.py": lambda path, mp: argv_main("studies/pusher_outcome", [str(path)], mp),
    "pointnav_report.py": lambda path, mp: argv_main("studies/pointnav_report", [str(path), str(path.parent / "r.png")],
                                                     mp),
    "bench_pointnav.py --checkpoint": lambda path, mp: argv_main("benchmarks/bench_pointnav",
                                                                 ["--checkpoint", str(path)], mp),
}


def argv_main(where: str, argv: list, monkeypatch):
    module = script(where, monkeypatch)
    monkeypatch.setattr(sys, "argv", [f"{where}.py", *argv])
    module.main()


@pytest.mark.parametrize("loader", LOADERS)
def test_hostile_checkpoint_is_refused(loader, hostile, monkeypatch):
    path, marker = hostile
    with pytest.raises(pickle.UnpicklingError, match="refused to load"):
        LOADERS[loader](path, monkeypatch)
    assert not marker.exists(), f"{loader} ran the checkpoint's code"


def test_no_torch_load_without_weights_only():
    """Every ``torch.load`` call in the package, scripts, benchmarks and studies passes ``weights_only=True`` (one does:
    ``load_checkpoint``), so a script added later cannot bring the full unpickler back unnoticed."""
    calls = []
    for folder in ("torchsim", "algos", "envs", "scripts", "benchmarks", "studies"):
        for path in sorted((REPO / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "load"
                        and isinstance(node.func.value, ast.Name) and node.func.value.id == "torch"):
                    safe = any(k.arg == "weights_only" and isinstance(k.value, ast.Constant) and k.value.value is True
                               for k in node.keywords)
                    calls.append((f"{path.relative_to(REPO)}:{node.lineno}", safe))
    assert calls and all(safe for _, safe in calls), [where for where, safe in calls if not safe]


def test_training_checkpoint_loads_everywhere(tmp_path, monkeypatch):
    """What the training code writes (config as a plain dict, RNG state as a tensor) passes ``weights_only``:
    evaluation, the viewer's loader and resume all read it."""
    run(tiny_ppo(), tmp_path)
    path = tmp_path / "checkpoints" / "last.pt"
    ckpt = load_checkpoint(path)
    assert isinstance(ckpt["cfg"], dict) and isinstance(ckpt["rng"], torch.Tensor)
    assert ckpt["counters"]["iteration"] == 2
    result = evaluate_cli.main([f"checkpoint={path}", "episodes=2", "max_steps=3"])
    assert result["env"] == "inverted_pendulum" and result["env_steps_trained"] == 32
    env, actor, name = script("scripts/view", monkeypatch).load(path)
    assert name == "inverted_pendulum" and actor is not None
    resumed = run(tiny_ppo(f"resume={path}", "budget.env_steps=48"), tmp_path / "resumed")
    assert resumed.env_steps == 48 and resumed.iteration == 3


# ------------------------------------------------------------------------------------------------------------ viewer
BALL = '<mujoco><worldbody><body><freejoint/><geom type="sphere" size="0.1"/></body></worldbody></mujoco>'


def ball_scene():
    import mujoco

    import torchsim
    from torchsim.render import Scene

    return Scene.build(mujoco.MjModel.from_xml_string(BALL), torchsim.load_mjcf(BALL))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_viewer_serves_this_machine_by_default():
    pytest.importorskip("viser", reason="viser not installed (pip install viser)")
    from torchsim.render.viewer import Viewer

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning about the network
        viewer = Viewer(ball_scene(), port=free_port(), verbose=False)
    try:
        assert viewer.server.get_host() == "127.0.0.1"
        assert viewer.url == f"http://127.0.0.1:{viewer.server.get_port()}"  # the host bound, not "localhost"
    finally:
        viewer.close()


def test_viewer_on_the_network_warns(monkeypatch):
    """``host="0.0.0.0"`` reaches the server, with a warning; the server is kept on the loopback here, so the test
    opens no port to the network."""
    viser = pytest.importorskip("viser", reason="viser not installed (pip install viser)")
    from torchsim.render.viewer import Viewer

    asked = []

    class LoopbackServer(viser.ViserServer):
        def __init__(self, host, port, **kwargs):
            asked.append(host)
            super().__init__(host="127.0.0.1", port=port, **kwargs)

    monkeypatch.setattr(viser, "ViserServer", LoopbackServer)
    with pytest.warns(UserWarning, match="listens on 0.0.0.0.*anyone who can reach this machine"):
        viewer = Viewer(ball_scene(), host="0.0.0.0", port=free_port(), verbose=False)
    viewer.close()
    assert asked == ["0.0.0.0"]


def test_loopback_hosts():
    from torchsim.render.viewer import is_loopback

    assert all(is_loopback(h) for h in ("127.0.0.1", "127.0.0.2", "::1", "localhost"))
    assert not any(is_loopback(h) for h in ("0.0.0.0", "::", "192.168.1.5", "example.org"))


def test_view_script_serves_this_machine_by_default(monkeypatch):
    view = script("scripts/view", monkeypatch)
    assert view.parser().parse_args([]).host == "127.0.0.1"
    assert view.parser().parse_args(["--host", "0.0.0.0"]).host == "0.0.0.0"
