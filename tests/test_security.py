"""Trust under hostile input: checkpoints load with ``weights_only`` (a pickle that would run code is refused by every
load path, before its code runs), and the browser viewer serves this machine only unless told otherwise."""

import ast
import pathlib
import pickle
import socket
import subprocess
import sys
import warnings

import pytest
import torch
from omegaconf import OmegaConf

from torchsim.algos import evaluate as evaluate_cli
from torchsim.algos.checkpoints import load_checkpoint, load_policy
from torchsim.algos.env_factory import make_env
from torchsim.algos.train import run
from tiny_runs import tiny_ppo

REPO = pathlib.Path(__file__).resolve().parent.parent


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


# every path by which the library reads a checkpoint: the loader, resume and the evaluation CLI; the scripts,
# benchmarks and studies read them through ``load_checkpoint`` (``test_no_unsafe_loads`` holds them to it)
LOADERS = {
    "load_checkpoint": lambda path: load_checkpoint(path),
    "resume": lambda path: run(tiny_ppo(f"resume={path}"), path.parent / "resumed"),
    "torchsim.evaluate": lambda path: evaluate_cli.main([f"checkpoint={path}"]),
}


@pytest.mark.parametrize("loader", LOADERS)
def test_hostile_checkpoint_is_refused(loader, hostile):
    path, marker = hostile
    with pytest.raises(pickle.UnpicklingError, match="refused to load"):
        LOADERS[loader](path)
    assert not marker.exists(), f"{loader} ran the checkpoint's code"


def test_no_unsafe_loads():
    """Every ``torch.load`` call in the package, scripts, benchmarks and studies passes ``weights_only=True`` (one does:
    ``load_checkpoint``) and none calls ``pickle.load``/``pickle.loads``, so a script added later cannot bring the
    full unpickler back unnoticed."""
    calls = []
    for folder in ("torchsim", "algos", "envs", "scripts", "benchmarks", "studies"):
        for path in sorted((REPO / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                        and isinstance(node.func.value, ast.Name)):
                    continue
                module, function = node.func.value.id, node.func.attr
                if module == "torch" and function == "load":
                    safe = any(k.arg == "weights_only" and isinstance(k.value, ast.Constant) and k.value.value is True
                               for k in node.keywords)
                    calls.append((f"{path.relative_to(REPO)}:{node.lineno}", safe))
                elif module == "pickle" and function in ("load", "loads"):
                    calls.append((f"{path.relative_to(REPO)}:{node.lineno}", False))
    assert calls and all(safe for _, safe in calls), [where for where, safe in calls if not safe]


def test_training_checkpoint_loads_everywhere(tmp_path):
    """What the training code writes (config as a plain dict, RNG state as a tensor) passes ``weights_only``:
    evaluation, the policy (as the viewer and the video script load it) and resume all read it."""
    run(tiny_ppo(), tmp_path)
    path = tmp_path / "checkpoints" / "last.pt"
    ckpt = load_checkpoint(path)
    assert isinstance(ckpt["cfg"], dict) and isinstance(ckpt["rng"], torch.Tensor)
    assert ckpt["counters"]["iteration"] == 2
    result = evaluate_cli.main([f"checkpoint={path}", "episodes=2", "max_steps=3"])
    assert result["env"] == "inverted_pendulum" and result["env_steps_trained"] == 32
    actor = load_policy(ckpt, make_env(OmegaConf.create(ckpt["cfg"]), 1, "cpu"), "cpu")
    assert actor is not None
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


def test_view_script_serves_this_machine_by_default():
    """The script as its users run it: its ``--help`` states the loopback default its parser holds."""
    usage = subprocess.run([sys.executable, str(REPO / "scripts" / "view.py"), "--help"], capture_output=True,
                           text=True, check=True).stdout
    assert "default 127.0.0.1: this machine only" in " ".join(usage.split())
