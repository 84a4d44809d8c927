"""Videos of PointNav episodes: the layout from above (walls, the path so far, the agent and its heading, the goal and
its success circle) beside the agent's depth image, one frame per step. Pure NumPy and Pillow, no GL.

    frames = [snapshot(env, 0)]            # after reset, then after each env.step
    save_gif(episode_frames(frames), "episode.gif", fps=10)
"""

from typing import NamedTuple

import numpy as np
from matplotlib import colormaps
from PIL import Image, ImageDraw

FREE, WALL = (236, 236, 236), (70, 70, 70)
PATH, AGENT, GOAL = (220, 40, 40), (30, 90, 220), (20, 160, 60)


class NavFrame(NamedTuple):
    """One env's view at one step: ``walls (G, G)`` bool occupancy of its layout (row = y cell, column = x cell),
    ``cell`` [m], the agent's ``pos (2,)`` [m] and ``heading`` [rad], ``goal (2,)`` [m], ``geodesic`` distance to
    the goal [m], ``depth (H, W)`` [m] clipped at ``max_depth``, and the ``success_distance`` [m]."""

    walls: np.ndarray
    cell: float
    pos: np.ndarray
    heading: float
    goal: np.ndarray
    geodesic: float
    depth: np.ndarray
    max_depth: float
    success_distance: float


def snapshot(env, row: int = 0) -> NavFrame:
    """Env ``row`` of a :class:`~torchsim.envs.nav.PointNav` now (copies, so the env can step on)."""
    return NavFrame(env.walls[env.layout[row]].cpu().numpy(), env.cell, env.pos[row].cpu().numpy().copy(),
                    float(env.heading[row]), env.goal[row].cpu().numpy().copy(), float(env.geo[row]),
                    env.depth[row, 0].cpu().numpy().copy(), env.max_depth, env.success_distance)


def episode_frames(frames: list[NavFrame], panel: int = 256) -> list[np.ndarray]:
    """RGB images ``(panel + 16, 2 * panel + 4, 3)`` uint8: the top-down map (y up) with the path up to each frame,
    and the depth image (near bright, far dark), over a caption line (step, geodesic distance to the goal)."""
    first = frames[0]
    grid = first.walls.shape[0]
    px_per_m = panel / (grid * first.cell)
    base = np.where(first.walls[::-1, :, None], WALL, FREE).astype(np.uint8)          # y up: flip rows
    base = np.asarray(Image.fromarray(base).resize((panel, panel), Image.NEAREST))
    lut = (colormaps["magma_r"](np.linspace(0.0, 1.0, 256))[:, :3] * 255).astype(np.uint8)

    def to_px(xy):
        return float(xy[0]) * px_per_m, panel - float(xy[1]) * px_per_m

    out, path = [], []
    for t, f in enumerate(frames):
        path.append(to_px(f.pos))
        canvas = Image.new("RGB", (2 * panel + 4, panel + 16), (255, 255, 255))
        top = Image.fromarray(base.copy())
        draw = ImageDraw.Draw(top)
        gx, gy = to_px(f.goal)
        r = f.success_distance * px_per_m
        draw.ellipse((gx - r, gy - r, gx + r, gy + r), outline=GOAL, width=2)
        draw.ellipse((gx - 2, gy - 2, gx + 2, gy + 2), fill=GOAL)
        if len(path) > 1:
            draw.line(path, fill=PATH, width=2)
        ax, ay = path[-1]
        hx, hy = ax + 10 * np.cos(f.heading), ay - 10 * np.sin(f.heading)
        draw.line((ax, ay, hx, hy), fill=AGENT, width=2)
        draw.ellipse((ax - 4, ay - 4, ax + 4, ay + 4), fill=AGENT)
        canvas.paste(top, (0, 0))
        shade = np.clip(f.depth / f.max_depth * 255, 0, 255).astype(np.uint8)
        canvas.paste(Image.fromarray(lut[shade]).resize((panel, panel), Image.NEAREST), (panel + 4, 0))
        ImageDraw.Draw(canvas).text((4, panel + 2), f"step {t:3d}   geodesic distance to goal {f.geodesic:5.2f} m",
                                    fill=(0, 0, 0))
        out.append(np.asarray(canvas))
    return out
