"""Camera images as observations of the torchsim envs (``TorchsimEnv(..., from_pixels=True)``).

The env renders every env's cameras in one :func:`torchsim.render.render` call from the state it has just reached
(after each step, and for the reset envs after a reset) and emits them as ``pixels``:

- ``pixel_kind="rgb"``: ``uint8`` in [0, 255], channels first, ``(B, 3 C, H, W)`` for ``C`` cameras (camera 0's
  red, green, blue, then camera 1's...);
- ``pixel_kind="depth"``: planar z-depth [m] in the env's dtype, ``(B, C, H, W)``; empty pixels hold the
  scene's ``zfar``.

With ``frame_stack=k`` the last ``k`` frames are stacked on the channel axis, oldest first (``(B, k x channels, H,
W)``); a reset env's stack holds ``k`` copies of its first frame. ``pixel_state`` says what ``observation`` holds
beside the images: ``"full"`` (the task's state vector, unchanged), ``"proprio"`` (the task's proprioceptive part
only, :data:`PIXEL_TASKS`: what a pixel policy may read without being handed what the images show), ``"none"``
(no ``observation`` key). ``pixel_privileged_state=True`` (an env option) also emits the task's full state vector as
``privileged_state``, for a critic that only trains in simulation (asymmetric actor-critic, Pinto et al. 2018): the
recipes' critics read it instead of the images, the policy never does.

Each task's default camera, colour mode and proprioception are in :data:`PIXEL_TASKS` (other tasks: a world
camera looking at the model's centre from the front-left, above, RGB, no proprioception subset).
"""

import math
from typing import Callable, NamedTuple

import torch
from torchrl.data import Bounded, Unbounded

from torchsim.render import Camera, Scene, render

PIXEL_KINDS = ("rgb", "depth")
PIXEL_STATES = ("full", "proprio", "none")


class PixelTask(NamedTuple):
    """A task's pixel defaults: ``camera(scene, mj_model)`` returns its default :class:`Camera`; ``kind`` is the
    default ``pixel_kind``; ``shading`` the RGB shading (``render``'s ``flat`` or ``lambert``); ``proprio``: the
    columns of the task's state observation that ``pixel_state="proprio"`` keeps (None: the task has none)."""

    camera: Callable
    kind: str = "rgb"
    shading: str = "lambert"
    proprio: tuple | None = None


def _overview(scene, m) -> Camera:
    """A world camera 2.2 model extents from the model's centre, from the front-left and above, seeing it whole."""
    centre, extent = m.stat.center, float(m.stat.extent)
    eye = centre + extent * torch.tensor([1.4, -1.4, 0.9]).numpy()
    return Camera.look_at(eye, centre, fovy=45.0, name="overview")


def _reacher_top(scene, m) -> Camera:
    """Straight down onto the arena from 0.55 m, +y up in the image: the square |x|, |y| < 0.23 m (the arm
    reaches 0.21 m, targets lie within 0.2 m) at 0.96 cm per pixel at 48x48; the 1.8-cm target and 2-cm fingertip
    always cover a pixel centre at that size."""
    return Camera.look_at((0.0, 0.0, 0.56), (0.0, 0.0, 0.01), up=(0.0, 1.0, 0.0), fovy=45.0, name="top")


def _pendulum_side(scene, m) -> Camera:
    """Riding on the cart, 1.5 m in front of it (-y), looking along +y at the pole: the window |x| < 0.45 m,
    -0.15 < z < 0.75 m around the cart (1.9 cm per pixel at 48x48; the pole's tip moves 12 cm at the 0.2-rad
    termination angle). The cart's place on the rail is not in the image (the rail looks the same everywhere)."""
    half = math.sqrt(0.5)
    return Camera.on_body(scene, "cart", pos=(0.0, -1.5, 0.3), quat=(half, half, 0.0, 0.0),
                          fovy=2 * math.degrees(math.atan(0.45 / 1.5)), name="side")


def pendulum_strip(scene, m) -> Camera:
    """Riding on the cart 1.5 m in front of it, a wide strip across the pole at z = 0.45 m: |x| < 0.3 m, for
    ``pixel_size=(24, 96)`` (0.63 cm per pixel; 0.2 rad of tilt moves the pole 9 cm, 14 pixels, across it)."""
    half = math.sqrt(0.5)
    return Camera.on_body(scene, "cart", pos=(0.0, -1.5, 0.45), quat=(half, half, 0.0, 0.0),
                          fovy=2 * math.degrees(math.atan(0.075 / 1.5)), name="strip")


#: Per task class name: default camera, kind, shading, proprioception columns. Reacher's proprioception: the
#: cos and sin of its 2 angles and their rates (columns 0-3, 6, 7), not the target or the fingertip-target vector;
#: the inverted pendulum's: the cart's position and velocity (columns 0 and 2), not the pole's angle or rate.
PIXEL_TASKS = {
    "Reacher": PixelTask(_reacher_top, kind="rgb", shading="flat", proprio=(0, 1, 2, 3, 6, 7)),
    "InvertedPendulum": PixelTask(_pendulum_side, kind="depth", proprio=(0, 2)),
}


class PixelObservation:
    """The image half of a pixel env's observation: the scene, the cameras, the image buffer and its spec.

    An observer of its env (``TorchsimEnv.observers``), which calls it where its state changes and where it emits:
    ``add_specs`` once, ``start`` at resets (every env, or ``rows``), ``advance`` after each step, ``fields`` for
    what the env emits, ``episode_state`` / ``load_episode_state`` with the env's running episodes."""

    def __init__(self, env, cameras=None, size=48, kind=None, state="full", frame_stack=1, compile=False,
                 supersample=1, privileged_state=False):
        task = PIXEL_TASKS.get(type(env).__name__, PixelTask(_overview))
        name = type(env).__name__
        self.scene = Scene.build(env.mj_model, env.sys, skip_unsupported=True)
        try:
            if cameras is None or callable(cameras):
                cameras = (task.camera if cameras is None else cameras)(self.scene, env.mj_model)
            self.camera = self.scene.camera(cameras)
        except (KeyError, IndexError, ValueError) as err:
            raise ValueError(f"{name}: bad camera {cameras!r}: {err.args[0]}") from None
        self.kind = task.kind if kind is None else kind
        if self.kind not in PIXEL_KINDS:
            raise ValueError(f"{name}: pixel_kind must be one of {PIXEL_KINDS}, got {self.kind!r}")
        if state not in PIXEL_STATES:
            raise ValueError(f"{name}: pixel_state must be one of {PIXEL_STATES}, got {state!r}")
        if state == "proprio" and task.proprio is None:
            raise ValueError(f"{name}: no proprioceptive observation is defined (envs/pixels.py, PIXEL_TASKS); "
                             "use pixel_state='full' or 'none'")
        self.state, self.shading, self.compile = state, task.shading, bool(compile)
        self.privileged_state = bool(privileged_state)
        self.proprio = None if task.proprio is None else torch.tensor(task.proprio, device=env.device)
        self.height, self.width = (int(size), int(size)) if isinstance(size, int) else map(int, size)
        self.frame_stack, self.supersample = int(frame_stack), int(supersample)
        if min(self.frame_stack, self.supersample, self.height, self.width) < 1:
            raise ValueError(f"{name}: frame_stack, pixel_supersample and pixel_size must be positive, got "
                             f"{frame_stack}, {supersample}, {size}")
        self.channels = self.camera.num * (3 if self.kind == "rgb" else 1)
        self.batch, self.device, self.dtype = env.batch_size, env.device, env.sys.dtype
        self.frames = None  # (B, frame_stack x channels, H, W), set by ``update``

    def observation_size(self, state_size: int) -> int | None:
        """Size of ``observation`` given the task's state observation size (None: no ``observation`` key)."""
        return {"full": state_size, "proprio": 0 if self.proprio is None else len(self.proprio), "none": None}[
            self.state]

    def add_specs(self, spec, state_size: int) -> None:
        """Add ``pixels`` to the env's observation ``spec`` (a Composite holding the task's ``observation``), resize
        or remove ``observation`` as ``pixel_state`` says, and add ``privileged_state`` if asked for."""
        observation = spec["observation"]
        spec["pixels"] = self.spec()
        size = self.observation_size(state_size)
        if size is None:
            del spec["observation"]
        else:
            spec["observation"] = Unbounded((*self.batch, size), dtype=observation.dtype, device=observation.device)
        if self.privileged_state:
            spec["privileged_state"] = observation.clone()

    def start(self, state, rows: torch.Tensor | None = None) -> None:
        """Episodes start: every env's (its stack restarts from ``state``'s frame), or those of ``rows`` only."""
        if rows is None:
            self.reset_stack()
        self.update(state, rows=rows)

    def advance(self, state, restart: torch.Tensor | None = None) -> None:
        """After a step: push ``state``'s frame (restarting the stacks of the mask ``restart``)."""
        self.update(state, restart=restart)

    def episode_state(self) -> dict:
        return {"frames": self.frames}

    def load_episode_state(self, saved: dict) -> None:
        self.frames = saved["frames"]

    def spec(self):
        shape = (*self.batch, self.frame_stack * self.channels, self.height, self.width)
        if self.kind == "rgb":
            return Bounded(0, 255, shape, dtype=torch.uint8, device=self.device)
        return Bounded(0.0, self.scene.zfar, shape, dtype=self.dtype, device=self.device)

    def render(self, state) -> torch.Tensor:
        """One frame ``(n, channels, H, W)`` of the ``n`` envs of ``state``."""
        k = self.supersample
        images = render(self.scene, state, self.camera, k * self.height, k * self.width, segmentation=False,
                        rgb=self.kind == "rgb", shading=self.shading, compile=self.compile)
        n = state.x_pos.shape[0]
        if self.kind == "depth":
            return self._pool(images.depth.reshape(n, self.channels, k * self.height, k * self.width))
        rgb = images.rgb.reshape(n, -1, k * self.height, k * self.width, 3).permute(0, 1, 4, 2, 3)
        rgb = self._pool(rgb.reshape(n, self.channels, k * self.height, k * self.width))
        return (rgb * 255.0).round().to(torch.uint8)

    def _pool(self, images: torch.Tensor) -> torch.Tensor:
        """The mean of each pixel's ``supersample x supersample`` sub-pixels: a geom covering part of a pixel shows
        as a blend (in depth, a blend of depths), so its edge moves smoothly, not a whole pixel at a time."""
        k = self.supersample
        return images if k == 1 else torch.nn.functional.avg_pool2d(images, k)

    def update(self, state, rows: torch.Tensor | None = None, restart: torch.Tensor | None = None) -> None:
        """Render ``state`` and store the frames, out of place (emitted images are never written again).

        ``rows`` (indices): only these envs were reset; their stacks restart from their new frame and ``state`` is
        rendered for them only. Else every env is rendered; the envs of the mask ``restart (B,)`` (or all, when
        there is no stack yet) restart their stack, the others push the new frame onto theirs."""
        if rows is not None:
            fresh = self.render(type(state)(*(x.index_select(0, rows) for x in state)))
            self.frames = self.frames.index_copy(0, rows, fresh.repeat(1, self.frame_stack, 1, 1))
            return
        frame = self.render(state)
        if self.frames is None or self.frame_stack == 1:
            self.frames = frame.repeat(1, self.frame_stack, 1, 1)
            return
        pushed = torch.cat((self.frames[:, self.channels:], frame), 1)
        if restart is not None:
            pushed = torch.where(restart[:, None, None, None], frame.repeat(1, self.frame_stack, 1, 1), pushed)
        self.frames = pushed

    def reset_stack(self) -> None:
        """Forget the stacks: the next ``update`` without ``rows`` restarts every env's."""
        self.frames = None

    def fields(self, entries: dict) -> dict:
        """The entries the env emits, from the task's (``observation``, the state vector, and ``goal_distance`` for
        goal tasks): ``pixels``, unless ``pixel_state="none"`` the task's state ``observation`` or its
        proprioceptive columns, and with ``privileged_state`` the whole state vector."""
        observation = entries["observation"]
        out = {**{k: v for k, v in entries.items() if k != "observation"}, "pixels": self.frames}
        if self.privileged_state:
            out["privileged_state"] = observation
        if self.state == "full":
            out["observation"] = observation
        elif self.state == "proprio":
            out["observation"] = observation.index_select(-1, self.proprio)
        return out
