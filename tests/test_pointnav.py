"""PointNav (torchsim.envs.nav): layouts, wall sliding, geodesic fields, depth, specs, the scripted follower."""

import math

import pytest
import torch
from torchrl.envs.utils import check_env_specs

import torchsim.envs
from torchsim.envs.nav import PointNav
from torchsim.envs.nav.geodesic import geodesic_field, geodesic_field_jacobi
from torchsim.envs.nav.layouts import collides, generate_layout, navigable, slide_move
from torchsim.envs.nav.pointnav import FORWARD, STOP, TURN_LEFT, TURN_RIGHT
from torchsim.envs.nav.raycast import column_rays, depth_image, row_rays, wall_distance

CELL, R = 0.2, 0.15


def room(g=20):
    w = torch.zeros(g, g, dtype=torch.bool)
    w[0, :] = w[-1, :] = w[:, 0] = w[:, -1] = True
    return w


def test_layouts_reproducible_connected_and_distinct():
    a, b, c = generate_layout(7), generate_layout(7), generate_layout(8)
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert a[0].all() and a[-1].all() and a[:, 0].all() and a[:, -1].all()
    walls = torch.stack([generate_layout(s) for s in range(6)])
    assert (walls.sum((1, 2)) > 4 * 63 + 40).all()          # interior walls: rooms, not one hall
    nav = navigable(walls)
    goal = torch.stack([n.nonzero()[0] for n in nav])
    d = geodesic_field(nav, goal)
    assert torch.equal(torch.isfinite(d), nav)               # every navigable cell reaches every other
    env = PointNav(2, num_layouts=3, split="test", layout_seed=5)
    assert env.layout_seeds == [2_000_005, 2_000_006, 2_000_007]
    assert torch.equal(env.walls[1], generate_layout(2_000_006))


def test_wall_sliding():
    w = room()
    w[:, 10] = True                                          # a wall: x in [2.0, 2.2]
    flat, lay = w.reshape(1, -1), torch.zeros(3, dtype=torch.long)
    pos = torch.tensor([[1.7, 1.0], [1.7, 1.0], [2.5, 1.0]])
    delta = torch.tensor([[0.2, 0.1], [0.25, 0.0], [-0.2, -0.15]])
    new = slide_move(flat, lay, pos, delta, 20, CELL, R)
    face = 2.0 - R - 1e-4
    assert new[0].tolist() == pytest.approx([face, 1.1], abs=1e-6)      # x stops at the wall, y slides on
    assert new[1].tolist() == pytest.approx([face, 1.0], abs=1e-6)
    assert new[2].tolist() == pytest.approx([2.2 + R + 1e-4, 0.85], abs=1e-6)
    again = slide_move(flat, lay, new, delta, 20, CELL, R)              # pressed against it: only y moves
    assert again[:, 0].tolist() == pytest.approx(new[:, 0].tolist(), abs=1e-6)
    assert not collides(w.expand(3, -1, -1), again, CELL, R).any()
    # a corner: blocked along x by the wall, and along y by the floor's border wall
    corner = slide_move(flat, lay[:1], torch.tensor([[1.7, 0.4]]), torch.tensor([[0.2, -0.2]]), 20, CELL, R)
    assert corner[0].tolist() == pytest.approx([face, 0.2 + R + 1e-4], abs=1e-6)


def test_geodesic_corridor_and_open_room():
    # an L corridor 3 cells wide: its navigable cells are its centre line, no corner can be cut
    w = torch.ones(20, 20, dtype=torch.bool)
    w[2:5, 2:16] = False       # along row 3, columns 3..15
    w[2:18, 13:16] = False     # up column 14, rows 3..16
    nav = navigable(w)
    assert nav.sum() == (14 - 3 + 1) + (16 - 3 + 1) - 1       # row 3, columns 3..14; column 14, rows 3..16
    d = geodesic_field(nav[None], torch.tensor([[3, 3]]))[0]
    assert d[3, 14].item() == pytest.approx(11)
    assert d[16, 14].item() == pytest.approx(11 + 13)
    assert d[3, 10].item() == pytest.approx(7)
    assert not torch.isfinite(d[nav.logical_not()]).any()
    # an open room: 8 neighbours and knight moves
    nav = navigable(room())
    d = geodesic_field(nav[None], torch.tensor([[9, 9]]))[0]
    for (di, dj), want in {(0, 5): 5, (1, 1): 2 ** 0.5, (1, 2): 5 ** 0.5, (3, 3): 3 * 2 ** 0.5,
                           (2, 4): 2 * 5 ** 0.5, (1, 3): 1 + 5 ** 0.5, (-4, 2): 2 * 5 ** 0.5}.items():
        assert d[9 + di, 9 + dj].item() == pytest.approx(want, rel=1e-6)
    # the raster passes agree with plain relaxation on generated layouts
    nav = navigable(torch.stack([generate_layout(s) for s in (11, 12)]))
    goal = torch.stack([n.nonzero()[n.sum() // 2] for n in nav])
    a, b = geodesic_field(nav, goal), geodesic_field_jacobi(nav, goal)
    assert torch.equal(torch.isfinite(a), torch.isfinite(b))
    assert torch.allclose(a[torch.isfinite(a)], b[torch.isfinite(b)], atol=1e-3)


def _render(w, pos, heading, n=64):
    xs, ys = column_rays(n, 90.0), row_rays(n, n, 90.0)
    t = wall_distance(w.reshape(1, -1), torch.zeros(1, dtype=torch.long), torch.tensor([pos]),
                      torch.tensor([heading]), xs, w.shape[0], CELL, 10.0)
    return depth_image(t, ys, 1.25, 2.5, 10.0)[0], xs, ys


def test_depth_against_closed_form():
    g = 128                                                   # 25.6 m: the border walls are beyond 10 m
    w = room(g)
    w[:, 100] = True                                          # a wall plane at x = 20.0
    d, y = 3.0, 12.8
    img, xs, ys = _render(w, (20.0 - d, y), 0.0)
    floor = 1.25 / -ys
    ceil = 1.25 / ys
    for i in range(64):
        want = min(d, floor[i].item() if ys[i] < 0 else ceil[i].item())
        assert img[i].tolist() == pytest.approx([want] * 64, abs=1e-5)   # planar: the same across the row
    assert img[32, 32].item() == pytest.approx(d, abs=1e-5)
    assert img[63, 0].item() == pytest.approx(1.25 / (1 - 1 / 64), abs=1e-5)   # bottom row: floor
    # turned left by 30 deg: a column's planar depth is d / (cos 30 + X sin 30); clipped at 10 m
    th = math.radians(30)
    img, xs, _ = _render(w, (20.0 - d, y), th)
    want = (d / (math.cos(th) + xs * math.sin(th))).clamp_max(10.0)
    assert img[32].tolist() == pytest.approx(want.tolist(), abs=1e-4)
    assert img[32, 63] < img[32, 0]          # the right columns now look closer to the wall's normal: nearer
    # facing away from the wall: nothing within 10 m at eye level, max depth
    img, _, _ = _render(w, (20.0 - d, y), math.pi)
    assert img[32].tolist() == pytest.approx([10.0] * 64)


def test_env_specs_registry_and_actions():
    env = torchsim.envs.make("pointnav", num_envs=3, num_layouts=4, seed=1)
    assert isinstance(env, PointNav)
    check_env_specs(env)
    check_env_specs(PointNav(2, num_layouts=2, one_hot_actions=True, image_size=16))
    td = env.reset()
    assert td["depth"].shape == (3, 1, 64, 64) and td["pointgoal"].shape == (3, 2)
    assert ((env.start_geo >= 1.0) & (env.start_geo <= 30.0)).all()
    assert (env.start_geo >= 1.1 * (env.goal - env.pos).norm(dim=-1) - 1e-4).all()
    h0, p0 = env.heading.clone(), env.pos.clone()
    td["action"] = torch.tensor([TURN_LEFT, TURN_RIGHT, FORWARD])
    out = env.step(td)["next"]
    turn = math.radians(10)
    assert torch.remainder(env.heading[:2] - h0[:2], 2 * math.pi).tolist() == pytest.approx(
        [turn, 2 * math.pi - turn], abs=1e-5)
    step = (env.pos[2] - p0[2]).norm().item()
    assert step <= 0.25 + 1e-6 and torch.equal(env.pos[:2], p0[:2])
    assert out["reward"][:, 0].tolist() == pytest.approx((env.start_geo - env.geo - 0.01).tolist(), abs=1e-5)
    assert not out["done"].any()
    rho, phi = out["pointgoal"][0]
    rel = env.goal[0] - env.pos[0]
    assert rho.item() == pytest.approx(rel.norm().item(), abs=1e-5)
    assert phi.item() == pytest.approx(math.remainder(math.atan2(rel[1], rel[0]) - env.heading[0].item(),
                                                      2 * math.pi), abs=1e-5)
    td = out.clone()
    td["action"] = torch.tensor([STOP, FORWARD, FORWARD])
    out = env.step(td)["next"]
    assert out["done"][:, 0].tolist() == [True, False, False] and out["terminated"][0]
    assert not out["success"][0] and out["spl"][0].item() == 0.0          # stopped metres from the goal
    # a partial reset leaves the other envs alone
    keep = env.pos[1:].clone()
    out["_reset"] = torch.tensor([[True], [False], [False]])
    env.reset(out)
    assert torch.equal(env.pos[1:], keep) and env.step_count.tolist() == [0, 2, 2]


def test_truncation():
    env = PointNav(2, num_layouts=2, episode_length=3, image_size=8)
    td = env.reset()
    for k in range(3):
        td["action"] = torch.tensor([TURN_LEFT, TURN_LEFT])
        out = env.step(td)["next"]
        td = out.clone()
    assert out["truncated"].all() and not out["terminated"].any() and out["done"].all()


def test_follower_succeeds_on_held_out_layouts():
    n = 12
    env = PointNav(n, num_layouts=6, split="test", image_size=8, seed=3)
    td = env.reset()
    start = env.start_geo.clone()
    finished = torch.zeros(n, dtype=torch.bool)
    success, spl, ret, geo, steps = (torch.zeros(n) for _ in range(5))
    for _ in range(env.episode_length):
        td["action"] = env.shortest_path_action()
        out = env.step(td)["next"]
        live = ~finished
        ret[live] += out["reward"][live, 0]
        done = out["done"][:, 0] & live
        success[done], spl[done] = out["success"][done, 0].float(), out["spl"][done, 0]
        geo[done], steps[done] = out["geodesic"][done, 0], env.step_count[done].float()
        finished |= done
        if finished.all():
            break
        td = out.clone()
    assert finished.all()
    assert success.mean() == 1.0 and spl.mean() >= 0.9
    # the return telescopes: progress - 0.01 per step + 2.5 SPL
    assert ret.tolist() == pytest.approx((start - geo - 0.01 * steps + 2.5 * spl).tolist(), abs=1e-3)
    assert (geo <= 0.2).all() and (steps < env.episode_length).all()


def test_random_walk_stays_out_of_walls():
    env = PointNav(32, num_layouts=8, image_size=8, seed=5)
    td = env.reset()
    gen = torch.Generator().manual_seed(1)
    for _ in range(60):
        a = torch.where(torch.rand(32, generator=gen) < 0.7, FORWARD, torch.randint(2, 4, (32,), generator=gen))
        before = env.pos.clone()
        td["action"] = a
        out, td = env.step_and_maybe_reset(td)
        assert not collides(env.walls[env.layout], env.pos, CELL, R).any()
        assert torch.isfinite(env.geodesic_at(env.pos, env.field)).all()
        kept = ~out["next", "done"][:, 0]           # envs not reset this step: turns don't move, moves <= 0.25 m
        moved = (env.pos - before).norm(dim=-1)
        assert (moved[kept & (a != FORWARD)] == 0).all() and (moved[kept] <= 0.25 + 1e-5).all()
