"""Pixel observations of the envs (``torchsim.envs.pixels``) and the pixel networks of the recipes."""

import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

import torchsim.envs as envs
from torchsim.algos.networks import make_actor, make_state_probe, make_value
from torchsim.render import Camera, render

torch.set_num_threads(1)

SMALL = dict(render_compile=False, pixel_size=24)


def random_steps(env, n, seed=0):
    torch.manual_seed(seed)
    td = env.reset()
    for _ in range(n):
        td = env.step(td.set("action", 2 * torch.rand(env.action_spec.shape) - 1))
        td = env.step_mdp(td)
    return td


@pytest.mark.parametrize("name", ["reacher_pixels", "inverted_pendulum_pixels"])
def test_check_env_specs(name):
    env = envs.make(name, 4, **SMALL)
    check_env_specs(env)
    spec = env.observation_spec["pixels"]
    channels = 3 if name == "reacher_pixels" else 4  # RGB; 4 stacked depth frames
    assert spec.shape == (4, channels, 24, 24)
    assert spec.dtype == (torch.uint8 if name == "reacher_pixels" else torch.float32)
    assert env.observation_spec["observation"].shape == (4, 6 if name == "reacher_pixels" else 2)
    # the critic's input: the task's whole state vector, of which the policy's observation is the proprioception
    env = envs.make(name, 4, pixel_privileged_state=True, **SMALL)
    check_env_specs(env)
    state_env = envs.make(name.removesuffix("_pixels"), 4)
    assert env.observation_spec["privileged_state"].shape == state_env.observation_spec["observation"].shape
    td = random_steps(env, 3)
    proprio = env.pixel_obs.proprio
    assert torch.equal(td["privileged_state"].index_select(-1, proprio), td["observation"])


def test_pendulum_strip_camera_sees_the_tilt():
    """The 24x96 strip (a camera given as a function of the scene): the pole's column moves with its angle."""
    env = envs.make("inverted_pendulum_pixels_strip", 3, render_compile=False)
    check_env_specs(env)
    assert env.observation_spec["pixels"].shape == (3, 2, 24, 96)
    env.set_state(torch.tensor([[0.0, -0.1], [0.0, 0.0], [0.5, 0.1]]), torch.zeros(3, 2))
    pole = env.pixel_obs.frames[:, -1] < 2.0  # (B, H, W): pixels that see the pole, the rest sees nothing
    column = (pole.float() * torch.arange(96.0)).sum((1, 2)) / pole.sum((1, 2))  # the pole's mean column
    assert abs(column[1] - 47.5) < 1  # upright: centred
    # 0.1 rad moves the pole 4.5 cm at the strip's 0.45 m, 7 pixels of 0.63 cm either way; the cart's place does
    # not matter (the camera rides on it)
    assert 5 < abs(column[0] - column[1]) < 9 and abs((column[0] + column[2]) / 2 - column[1]) < 1


def test_options_shapes_and_specs():
    cams = [Camera.look_at((0, -1, 1), (0, 0, 0)), Camera.look_at((1, 0, 1), (0, 0, 0))]
    env = envs.make("reacher", 3, from_pixels=True, cameras=cams, pixel_size=(16, 20), pixel_kind="depth",
                    pixel_state="none", frame_stack=3)
    check_env_specs(env)
    td = env.reset()
    assert td["pixels"].shape == (3, 6, 16, 20) and td["pixels"].dtype == torch.float32
    assert "observation" not in td.keys() and "observation" not in env.observation_spec.keys()
    assert "pixels" not in envs.make("reacher", 2).reset().keys()  # the state env is as before
    env = envs.make("ant", 2, from_pixels=True, **SMALL)  # a task without pixel defaults: the overview camera
    check_env_specs(env)
    assert env.observation_spec["pixels"].shape == (2, 3, 24, 24)
    assert env.reset()["pixels"].float().std() > 0  # the ant is in view, not an empty frame
    with pytest.raises(ValueError, match="no proprioceptive observation"):
        envs.make("ant", 2, from_pixels=True, pixel_state="proprio")
    with pytest.raises(ValueError, match="pixel_privileged_state needs from_pixels"):
        envs.make("reacher", 2, pixel_privileged_state=True)


def test_supersampled_pixels_average_a_finer_render():
    """``pixel_supersample=k``: each pixel is the mean of a k-times finer render's k x k block, so a pole edge that
    crosses a pixel shows as a blend of the two colours instead of jumping a whole pixel."""
    env = envs.make("inverted_pendulum_pixels", 3, pixel_kind="rgb", pixel_supersample=3, render_compile=False,
                    pixel_size=16)
    td = random_steps(env, 2)
    fine = render(env.pixel_obs.scene, env.state, env.pixel_obs.camera, 48, 48, rgb=True).rgb  # (B, 48, 48, 3)
    pooled = torch.nn.functional.avg_pool2d(fine.permute(0, 3, 1, 2), 3)
    assert torch.equal(td["pixels"][:, -3:], (pooled * 255).round().to(torch.uint8))  # the newest frame
    coarse = render(env.pixel_obs.scene, env.state, env.pixel_obs.camera, 16, 16, rgb=True).rgb
    distinct = lambda images: len(torch.unique(images.reshape(-1, 3), dim=0))  # noqa: E731
    assert distinct(pooled) > distinct(coarse)  # blended edge colours


def test_pixels_equal_a_direct_render_of_the_state():
    env = envs.make("reacher_pixels", 5, render_compile=False)  # the training size, 48x48
    td = random_steps(env, 3)
    scene, cam = env.pixel_obs.scene, env.pixel_obs.camera
    rgb = render(scene, env.state, cam, 48, 48, rgb=True, shading="flat").rgb  # (B, H, W, 3) in [0, 1]
    expected = (rgb * 255).round().to(torch.uint8).permute(0, 3, 1, 2)
    assert torch.equal(td["pixels"], expected)
    # at 48x48 every env's image shows the target (reacher.xml's red, 0.9 0.2 0.2) and the fingertip
    for colour in ((230, 51, 51), (0, 204, 153)):
        seen = (td["pixels"] == torch.tensor(colour, dtype=torch.uint8)[:, None, None]).all(1).flatten(1).any(1)
        assert seen.all(), colour
    # proprioception: the state observation's angle and rate columns, not the target
    full = env._observation(env.state, env._zero_ctrl())
    assert torch.equal(td["observation"], full[:, [0, 1, 2, 3, 6, 7]])

    env = envs.make("inverted_pendulum_pixels", 4, **SMALL)
    before = random_steps(env, 2)["pixels"]
    td = env.step(TensorDict(action=torch.full((4, 1), 0.5), pixels=before, batch_size=[4]))
    depth = render(scene := env.pixel_obs.scene, env.state, env.pixel_obs.camera, 24, 24).depth
    after = td["next", "pixels"]
    assert torch.equal(after[:, -1], depth)  # the newest frame last
    assert torch.equal(after[:, :-1], before[:, 1:])  # the others moved down the stack, the oldest dropped
    assert ((depth > 1.0) & (depth < 2.0)).any() and (depth == scene.zfar).any()  # pole at ~1.5 m, background


@pytest.mark.parametrize("name", ["reacher_pixels", "inverted_pendulum_pixels"])
def test_partial_reset_leaves_other_envs_images(name):
    env = envs.make(name, 6, **SMALL)
    td = random_steps(env, 4)
    before, q_before = td["pixels"], env.state.q.clone()
    mask = torch.tensor([True, False, False, True, False, False])
    # what the env emits (TorchRL's reset then takes the other envs' entries from the tensordict it was given)
    after = env._reset(TensorDict(_reset=mask[:, None], batch_size=[6]))["pixels"]
    keep = ~mask
    assert torch.equal(after[keep], before[keep])
    assert torch.equal(env.state.q[keep], q_before[keep])
    fresh = env.pixel_obs.render(env.state)  # every env's image of its current state
    stack = env.pixel_obs.frame_stack
    assert torch.equal(after[mask], fresh[mask].repeat(1, stack, 1, 1))  # a restarted stack: copies of frame 1
    assert torch.equal(after[keep][:, -fresh.shape[1]:], fresh[keep])
    assert not torch.equal(after[mask], before[mask])
    # through TorchRL's reset, as a collector calls it
    assert torch.equal(env.reset(td.set("_reset", mask[:, None]))["pixels"][keep], before[keep])


def test_native_autoreset_restarts_the_finished_envs_stacks():
    env = envs.make("inverted_pendulum_pixels", 4, native_autoreset=True, episode_length=3, **SMALL)
    td = random_steps(env, 2)
    out = env.step(td.set("action", torch.zeros(4, 1)))["next"]
    assert out["done"].all()
    frames = out["pixels"]
    assert torch.equal(frames[:, 0], frames[:, 1])  # every env restarted: its stack holds its first frame twice
    assert torch.equal(frames[:, 1], env.pixel_obs.render(env.state)[:, 0])


def test_bad_camera_and_options_give_clear_errors():
    with pytest.raises(ValueError, match=r"Reacher: bad camera 'nope'.*no camera named 'nope'"):
        envs.make("reacher", 2, from_pixels=True, cameras="nope")
    with pytest.raises(ValueError, match="out of range"):
        envs.make("reacher", 2, from_pixels=True, cameras=3)
    with pytest.raises(ValueError, match="pixel_kind must be one of"):
        envs.make("reacher", 2, from_pixels=True, pixel_kind="segmentation")
    with pytest.raises(ValueError, match="pixel_state must be one of"):
        envs.make("reacher", 2, from_pixels=True, pixel_state="some")


def test_pixel_networks():
    cfg = OmegaConf.create({"hidden": [16], "activation": "silu", "cnn": {"channels": [4, 8], "kernels": [3, 3],
                                                                          "strides": [2, 2], "features": 8}})
    for name, privileged in (("reacher_pixels", False), ("inverted_pendulum_pixels", False),
                             ("inverted_pendulum_pixels", True)):
        env = envs.make(name, 3, pixel_privileged_state=privileged, **SMALL)
        td = env.rollout(2, break_when_any_done=False)  # (B, T) leading dims, as PPO's GAE sees them
        actor, critic = make_actor(env, cfg, "cpu"), make_value(env, cfg, "cpu", with_action=False)
        assert set(actor.in_keys) == {"pixels", "observation"}  # never the privileged state
        out = critic(actor(td.clone()))
        assert out["action"].shape == (3, 2, env.action_spec.shape[-1]) and out["state_value"].shape == (3, 2, 1)
        q = make_value(env, cfg, "cpu", with_action=True)(td.clone())["state_action_value"]
        assert q.shape == (3, 2, 1)
        # the image matters to the policy, and to the critic unless it reads the privileged state instead
        blank = td.clone().set("pixels", torch.zeros_like(td["pixels"]))
        assert not torch.allclose(actor(blank.clone())["loc"], actor(td.clone())["loc"])
        assert critic.in_keys == (["privileged_state"] if privileged else ["pixels", "observation"])
        assert torch.allclose(critic(blank)["state_value"], out["state_value"]) == privileged


def test_state_probe_trains_the_policy_cnn():
    """``algo.state_probe_coeff``'s auxiliary loss reads the policy's own CNN features: its gradient reaches the
    policy's conv layers (not its MLP head), and Adam steps on one batch fit what the images show (the pole's
    angle: the camera rides on the cart, so its position and velocity are not in view); refused without
    ``privileged_state``; none at coefficient 0."""
    cfg = OmegaConf.create({"hidden": [16], "activation": "silu", "cnn": {"channels": [4, 8], "kernels": [3, 3],
                                                                          "strides": [2, 2], "features": 8}})
    env = envs.make("inverted_pendulum_pixels", 16, **SMALL)
    td = random_steps(env, 10)
    actor = make_actor(env, cfg, "cpu")
    probe = make_state_probe(actor, env, 1.0, "cpu")
    assert any(probe.encoder is m for m in actor.modules())
    probe(td["pixels"], td["privileged_state"]).backward()
    assert probe.encoder.conv[0].weight.grad.abs().sum() > 0 and probe.readout.weight.grad.abs().sum() > 0
    assert all(p.grad is None for p in probe.encoder.head.parameters())
    optim = torch.optim.Adam(probe.parameters(), 1e-2)
    for _ in range(100):
        loss = probe(td["pixels"], td["privileged_state"])
        optim.zero_grad()
        loss.backward()
        optim.step()
    angle = td["privileged_state"][:, 1]  # (cart position, pole angle, their rates)
    with torch.no_grad():
        residual = probe.readout(probe.encoder.features(td["pixels"]))[:, 1] - angle
    assert residual.square().mean().sqrt() < 0.3 * angle.std()
    assert make_state_probe(actor, env, 0.0, "cpu") is None
    with pytest.raises(ValueError, match="privileged_state"):
        make_state_probe(actor, envs.make("inverted_pendulum_pixels", 2, pixel_privileged_state=False, **SMALL), 1.0,
                         "cpu")
