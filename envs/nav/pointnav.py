"""PointNav (Habitat's definition) in procedural grid layouts, as a batched TorchRL env. See docs/navigation.md."""

import math

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, OneHot, Unbounded
from torchrl.envs import EnvBase

from torchsim.envs.nav.geodesic import geodesic_field
from torchsim.envs.nav.layouts import generate_layout, navigable, slide_move
from torchsim.envs.nav.raycast import column_rays, depth_image, row_rays, wall_distance

STOP, FORWARD, TURN_LEFT, TURN_RIGHT = 0, 1, 2, 3
#: First layout seed of each split: layouts of different splits never share a seed (held-out layouts).
SPLIT_SEEDS = {"train": 0, "val": 1_000_000, "test": 2_000_000}


class PointNav(EnvBase):
    """Point-goal navigation: reach a goal given in polar coordinates, seeing only depth.

    Batched over ``num_envs``; ``num_layouts`` layouts (:func:`generate_layout`, seeds ``SPLIT_SEEDS[split] +
    layout_seed + k``) are resident and shared; each reset puts the env in a uniformly drawn one, with a new
    episode: goal and start drawn uniformly on navigable cell centres with geodesic distance in
    ``[min_geodesic, max_geodesic]`` m and geodesic / Euclidean ratio >= ``min_ratio`` (rejection), heading
    uniform. The goal's geodesic distance field is computed (batched wavefront) at reset and looked up per step.

    Actions (``Categorical(4)``, or ``OneHot(4)`` with ``one_hot_actions``): 0 STOP, 1 FORWARD ``forward_step`` m,
    2 TURN_LEFT and 3 TURN_RIGHT by ``turn_deg``. The agent is a square of half-width ``agent_radius``; a blocked
    move slides along the wall. An episode ends on STOP (terminated) or after ``episode_length`` steps
    (truncated). Success: STOP with geodesic distance to the goal <= ``success_distance``; SPL = success *
    l / max(l, p) (l the start's geodesic distance, p the path taken). Reward: decrease of the geodesic distance -
    ``slack_reward`` per step + ``success_reward`` * SPL on the last step.

    Emits ``depth (B, 1, H, W)`` planar depth [m] clipped to ``max_depth`` (camera ``camera_height`` m high,
    ``hfov`` deg), ``pointgoal (B, 2)`` = (distance [m], angle [rad] counter-clockwise from the heading) of the
    goal, ``geodesic (B, 1)`` the current geodesic distance [m] (for logging, not for the policy), and
    ``success``, ``spl`` (B, 1) (nonzero only on an episode's last step).
    """

    def __init__(self, num_envs: int = 1, *, device="cpu", num_layouts: int = 64, split: str = "train",
                 layout_seed: int = 0, grid_size: int = 64, cell: float = 0.2, image_size: int = 64,
                 hfov: float = 90.0, camera_height: float = 1.25, ceiling: float | None = 2.5,
                 max_depth: float = 10.0, agent_radius: float = 0.15, forward_step: float = 0.25,
                 turn_deg: float = 10.0, episode_length: int = 500, success_distance: float = 0.2,
                 min_geodesic: float = 1.0, max_geodesic: float = 30.0, min_ratio: float = 1.1,
                 slack_reward: float = 0.01, success_reward: float = 2.5, one_hot_actions: bool = False,
                 seed: int | None = None):
        if int(num_envs) < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs}")
        if split not in SPLIT_SEEDS:
            raise ValueError(f"split must be one of {list(SPLIT_SEEDS)}, got {split!r}")
        if not 0.5 * cell < agent_radius < 1.5 * cell:
            raise ValueError("agent_radius must lie between half a cell and 1.5 cells (navigable(): 3x3 clearance)")
        super().__init__(device=device, batch_size=torch.Size([int(num_envs)]))
        self.size, self.cell, self.radius = int(grid_size), float(cell), float(agent_radius)
        self.image_size, self.hfov, self.camera_height = int(image_size), float(hfov), float(camera_height)
        self.ceiling, self.max_depth = ceiling, float(max_depth)
        self.forward_step, self.turn = float(forward_step), math.radians(turn_deg)
        self.episode_length, self.success_distance = int(episode_length), float(success_distance)
        self.min_geodesic, self.max_geodesic, self.min_ratio = float(min_geodesic), float(max_geodesic), min_ratio
        self.slack_reward, self.success_reward = float(slack_reward), float(success_reward)
        self.one_hot_actions = bool(one_hot_actions)
        self.layout_seeds = [SPLIT_SEEDS[split] + int(layout_seed) + k for k in range(int(num_layouts))]
        walls = torch.stack([generate_layout(s, self.size) for s in self.layout_seeds]).to(self.device)
        self.walls = walls                                   # (L, G, G) bool, shared by all envs
        self.walls_flat = walls.reshape(len(walls), -1)
        self.nav = navigable(walls)                          # (L, G, G) bool
        self.rng = torch.Generator(device=self.device)
        self.rng.manual_seed(0 if seed is None else int(seed))
        self._xs = column_rays(self.image_size, self.hfov, self.device)
        self._ys = row_rays(self.image_size, self.image_size, self.hfov, self.device)
        b, g, dev = self.batch_size[0], self.size, self.device
        self.layout = torch.zeros(b, dtype=torch.long, device=dev)
        self.pos = torch.zeros(b, 2, device=dev)
        self.heading = torch.zeros(b, device=dev)
        self.goal = torch.zeros(b, 2, device=dev)
        self.field = torch.zeros(b, g * g, device=dev)       # geodesic distance [m] to the goal, per cell
        self.geo = torch.zeros(b, device=dev)
        self.start_geo = torch.ones(b, device=dev)
        self.path_len = torch.zeros(b, device=dev)
        self.step_count = torch.zeros(b, dtype=torch.long, device=dev)
        self.depth = torch.zeros(b, 1, self.image_size, self.image_size, device=dev)
        self._make_specs()
        self._new_episodes(torch.arange(b, device=dev))

    # ------------------------------------------------------------------------------------------------ specs
    def _make_specs(self) -> None:
        shape, dev, n = self.batch_size, self.device, self.image_size
        flag = lambda: Categorical(2, (*shape, 1), dtype=torch.bool, device=dev)  # noqa: E731
        self.observation_spec = Composite(
            depth=Bounded(0.0, self.max_depth, (*shape, 1, n, n), dtype=torch.float32, device=dev),
            pointgoal=Unbounded((*shape, 2), dtype=torch.float32, device=dev),
            geodesic=Unbounded((*shape, 1), dtype=torch.float32, device=dev),
            success=flag(),
            spl=Bounded(0.0, 1.0, (*shape, 1), dtype=torch.float32, device=dev),
            shape=shape)
        if self.one_hot_actions:
            self.action_spec = OneHot(4, (*shape, 4), dtype=torch.long, device=dev)
        else:
            self.action_spec = Categorical(4, shape, dtype=torch.long, device=dev)
        self.reward_spec = Unbounded((*shape, 1), dtype=torch.float32, device=dev)
        self.full_done_spec = Composite(done=flag(), terminated=flag(), truncated=flag(), shape=shape)

    def _set_seed(self, seed: int | None) -> None:
        if seed is not None:
            self.rng.manual_seed(int(seed))

    #: what an env's running episode holds (besides the generator of the draws, ``rng``)
    EPISODE_FIELDS = ("layout", "pos", "heading", "goal", "field", "geo", "start_geo", "path_len", "step_count",
                      "depth")

    def episode_state(self) -> dict:
        """The running episodes and the generator that draws the next ones, as tensors; ``load_episode_state`` puts
        them back, and the episodes go on as they would have (a training checkpoint holds them, so that a resumed
        run continues)."""
        return {**{name: getattr(self, name) for name in self.EPISODE_FIELDS}, "rng": self.rng.get_state()}

    def load_episode_state(self, saved: dict) -> None:
        """Continue the episodes of ``saved`` (``episode_state``, of an env of this split and batch)."""
        for name in self.EPISODE_FIELDS:
            setattr(self, name, saved[name])
        self.rng.set_state(saved["rng"].cpu())  # a generator's state is a CPU ByteTensor, whatever its device

    # ------------------------------------------------------------------------------------------ geometry
    def cell_centres(self, cells: torch.Tensor) -> torch.Tensor:
        """Centres [m] (x, y) of flat cell indices ``cells``."""
        return torch.stack([cells % self.size, cells // self.size], -1).float().add(0.5).mul(self.cell)

    def geodesic_at(self, pos: torch.Tensor, field: torch.Tensor) -> torch.Tensor:
        """Geodesic distance [m] from ``pos (n, 2)`` to the goal: the least ``field[c] + |pos - centre(c)|`` over
        the 3x3 cells around ``pos`` (each in straight sight of ``pos``); ``inf`` if none is navigable."""
        g = self.size
        ij = torch.floor(pos / self.cell).long()
        off = torch.arange(-1, 2, device=pos.device)
        cj = (ij[:, 0:1, None] + off[None, None, :]).clamp(0, g - 1)      # (n, 1, 3) columns
        ci = (ij[:, 1:2, None] + off[None, :, None]).clamp(0, g - 1)      # (n, 3, 1) rows
        cells = (ci * g + cj).reshape(-1, 9)
        d = field.gather(1, cells) + (self.cell_centres(cells) - pos[:, None, :]).norm(dim=-1)
        return d.amin(1)

    def render(self, rows: torch.Tensor | None = None) -> torch.Tensor:
        """Depth images ``(n, 1, H, W)`` of envs ``rows`` (all by default) at their current poses."""
        sel = slice(None) if rows is None else rows
        t = wall_distance(self.walls_flat, self.layout[sel], self.pos[sel], self.heading[sel], self._xs, self.size,
                          self.cell, self.max_depth)
        return depth_image(t, self._ys, self.camera_height, self.ceiling, self.max_depth)[:, None]

    def pointgoal(self) -> torch.Tensor:
        rel = self.goal - self.pos
        ang = torch.atan2(rel[:, 1], rel[:, 0]) - self.heading
        return torch.stack([rel.norm(dim=-1), torch.atan2(torch.sin(ang), torch.cos(ang))], -1)

    # ------------------------------------------------------------------------------------------- episodes
    def _new_episodes(self, rows: torch.Tensor, tries: int = 50) -> None:
        """Draw a layout and an episode for each env in ``rows``, compute its goal's geodesic field, render."""
        for k in range(0, rows.numel(), 256):     # chunks bound the wavefront's memory
            self._draw_episodes(rows[k:k + 256], tries)
        self.heading[rows] = torch.rand(rows.numel(), generator=self.rng, device=self.device) * (2 * math.pi)
        self.geo[rows] = self.geodesic_at(self.pos[rows], self.field[rows])
        self.start_geo[rows] = self.geo[rows]
        self.path_len[rows] = 0.0
        self.step_count[rows] = 0
        self.depth[rows] = self.render(rows)

    def _draw_episodes(self, rows: torch.Tensor, tries: int) -> None:
        g, dev = self.size, self.device
        self.layout[rows] = torch.randint(len(self.layout_seeds), (rows.numel(),), generator=self.rng, device=dev)
        pending = rows
        for _ in range(tries):
            if pending.numel() == 0:
                break
            nav = self.nav[self.layout[pending]]
            goal = torch.multinomial(nav.reshape(-1, g * g).float(), 1, generator=self.rng).squeeze(1)
            field = geodesic_field(nav, torch.stack([goal // g, goal % g], -1)).reshape(-1, g * g) * self.cell
            cells = torch.arange(g * g, device=dev)
            euclid = (self.cell_centres(cells)[None] - self.cell_centres(goal)[:, None]).norm(dim=-1)
            ok = (nav.reshape(-1, g * g) & (field >= self.min_geodesic) & (field <= self.max_geodesic)
                  & (field >= self.min_ratio * euclid))
            found = ok.any(1)
            start = torch.multinomial((ok | ~found[:, None]).float(), 1, generator=self.rng).squeeze(1)
            done = pending[found]
            self.field[done] = field[found]
            self.goal[done] = self.cell_centres(goal[found])
            self.pos[done] = self.cell_centres(start[found])
            pending = pending[~found]   # goals with no valid start: draw again (layout included)
            self.layout[pending] = torch.randint(len(self.layout_seeds), (pending.numel(),), generator=self.rng,
                                                 device=dev)
        if pending.numel():
            raise RuntimeError(f"no valid PointNav episode found in {tries} goal draws for {pending.numel()} envs")

    def _observation(self, success=None, spl=None) -> TensorDict:
        b = self.batch_size[0]
        if success is None:
            success = torch.zeros(b, dtype=torch.bool, device=self.device)
            spl = torch.zeros(b, device=self.device)
        return TensorDict(depth=self.depth.clone(), pointgoal=self.pointgoal(), geodesic=self.geo[:, None].clone(),
                          success=success[:, None], spl=spl[:, None], batch_size=self.batch_size, device=self.device)

    def _reset(self, tensordict: TensorDictBase | None, **kwargs) -> TensorDictBase:
        mask = None if tensordict is None else tensordict.get("_reset", None)
        if mask is None:
            rows = torch.arange(self.batch_size[0], device=self.device)
        else:
            rows = mask.reshape(self.batch_size).nonzero().squeeze(-1)
        if rows.numel():
            self._new_episodes(rows)
        out = self._observation()
        no = torch.zeros((*self.batch_size, 1), dtype=torch.bool, device=self.device)
        out.update(dict(done=no, terminated=no.clone(), truncated=no.clone()))
        return out

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action")
        if self.one_hot_actions:
            action = action.argmax(-1)
        action = action.reshape(self.batch_size).to(self.device)
        stop = action == STOP
        fwd = (action == FORWARD).float()
        self.heading = self.heading + self.turn * ((action == TURN_LEFT).float() - (action == TURN_RIGHT).float())
        self.heading = torch.remainder(self.heading, 2 * math.pi)
        delta = self.forward_step * fwd[:, None] * torch.stack([torch.cos(self.heading), torch.sin(self.heading)], -1)
        new = slide_move(self.walls_flat, self.layout, self.pos, delta, self.size, self.cell, self.radius,
                         self.forward_step)
        self.path_len = self.path_len + (new - self.pos).norm(dim=-1)
        self.pos = new
        before = self.geo
        geo = self.geodesic_at(new, self.field)
        self.geo = torch.where(torch.isfinite(geo), geo, before)
        self.step_count += 1
        success = stop & (self.geo <= self.success_distance)
        terminated = stop
        truncated = (self.step_count >= self.episode_length) & ~stop
        done = terminated | truncated
        spl = success.float() * self.start_geo / torch.maximum(self.start_geo, self.path_len)
        reward = (before - self.geo) - self.slack_reward + self.success_reward * spl
        self.depth = self.render()
        out = self._observation(success, spl)
        out.update(dict(reward=reward[:, None], done=done[:, None], terminated=terminated[:, None],
                        truncated=truncated[:, None]))
        return out

    # ---------------------------------------------------------------------------------------- oracle
    def shortest_path_action(self) -> torch.Tensor:
        """The scripted follower's actions ``(B,)``: STOP within ``success_distance`` (geodesic) of the goal; else
        head for the cell of least geodesic distance among the 5x5 cells around the agent: FORWARD when the
        heading is within half a turn of it, else turn towards it."""
        g = self.size
        ij = torch.floor(self.pos / self.cell).long()
        off = torch.arange(-2, 3, device=self.device)
        cj = (ij[:, 0:1, None] + off[None, None, :]).clamp(0, g - 1)
        ci = (ij[:, 1:2, None] + off[None, :, None]).clamp(0, g - 1)
        cells = (ci * g + cj).reshape(-1, 25)
        best = cells.gather(1, self.field.gather(1, cells).argmin(1, keepdim=True)).squeeze(1)
        rel = self.cell_centres(best) - self.pos
        err = torch.atan2(rel[:, 1], rel[:, 0]) - self.heading
        err = torch.atan2(torch.sin(err), torch.cos(err))
        act = torch.where(err.abs() <= self.turn / 2 + 1e-4, FORWARD, torch.where(err > 0, TURN_LEFT, TURN_RIGHT))
        return torch.where(self.geo <= self.success_distance, STOP, act)
