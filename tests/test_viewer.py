"""The browser viewer (``torchsim.render.viewer``) and torchsim-rendered videos (``torchsim.envs.video``).

The browser test opens saved viewer files in headless Chromium (Debian package ``chromium``) and checks that the
screenshot shows each body where the state puts it: the centroid of the body's coloured pixels against the pinhole
projection of its position through the saved camera. Skipped, with the reason, where Chromium or viser is absent.
"""

import shutil
import subprocess

import numpy as np
import pytest
import torch

import torchsim
from torchsim.render import Camera, Scene, render

# a green ball and a blue cube, free bodies, nothing else (no floor: an empty background)
TWO_BODIES = """
<mujoco>
  <worldbody>
    <body name="ball" pos="0 0 0"><freejoint/><geom type="sphere" size="0.15" rgba="0 0.8 0 1"/></body>
    <body name="cube" pos="0 0 0"><freejoint/><geom type="box" size="0.12 0.12 0.12" rgba="0 0 0.9 1"/></body>
  </worldbody>
</mujoco>
"""
EYE, TARGET, FOVY = (0.0, -3.0, 0.0), (0.0, 0.0, 0.0), 45.0
VIEW_W, VIEW_H = 640, 480


def two_bodies(ball, cube):
    """The model's Scene and a State with the ball's and the cube's centres at ``ball`` and ``cube``."""
    import mujoco

    system = torchsim.load_mjcf(TWO_BODIES)
    scene = Scene.build(mujoco.MjModel.from_xml_string(TWO_BODIES), system)
    q = torch.tensor([[*ball, 1.0, 0.0, 0.0, 0.0, *cube, 1.0, 0.0, 0.0, 0.0]])
    state = torchsim.init(system, q, torch.zeros(1, system.nv))
    return system, scene, state


def project(point, width, height):
    """Pixel (column, row) of a world point through the camera EYE -> TARGET, +z up, vertical FOVY."""
    eye, target = np.array(EYE), np.array(TARGET)
    z = (eye - target) / np.linalg.norm(eye - target)
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    d = np.asarray(point, dtype=np.float64) - eye
    f = (height / 2) / np.tan(np.deg2rad(FOVY) / 2)
    return width / 2 + f * (d @ x) / -(d @ z), height / 2 - f * (d @ y) / -(d @ z)


def centroid(rgb, channel):
    """(column, row) centroid and pixel count of the silhouette of the body coloured ``channel`` (1 green, 2 blue).

    Shading-independent, because the browser's lighting varies between machines (a brighter specular highlight
    once whitened the top of the ball and moved a colour-threshold centroid 2.6 px down): a pixel is the body's
    where it is off the white background and ``channel`` is its largest by 15/255 (the viewer's notices are orange
    and grey); each row of the silhouette is then filled between its first and last such pixel, which restores a
    white highlight inside the convex outline of a sphere or a box."""
    rgb = rgb.astype(np.int32)
    others = [c for c in range(3) if c != channel]
    coloured = ((765 - rgb.sum(-1)) > 60) & (rgb[..., channel] > rgb[..., others[0]] + 15) \
        & (rgb[..., channel] > rgb[..., others[1]] + 15)
    columns = np.arange(rgb.shape[1])
    first = np.where(coloured, columns, rgb.shape[1]).min(1, keepdims=True)
    last = np.where(coloured, columns, -1).max(1, keepdims=True)
    mask = (columns >= first) & (columns <= last)
    rows, cols = np.nonzero(mask)
    # pixel (i, j) covers [j, j + 1) x [i, i + 1): its centre is half a pixel on, as in segmentation_centroids
    return (cols.mean() + 0.5 if len(cols) else np.nan, rows.mean() + 0.5 if len(rows) else np.nan), int(mask.sum())


def segmentation_centroids(scene, state, width, height):
    """(column, row) centroid of each geom's pixels in torchsim's own renderer (the exact perspective image of
    the state, same camera), by geom id."""
    seg = render(scene, state, Camera.look_at(EYE, TARGET, fovy=FOVY), height, width).segmentation[0].numpy()
    out = {}
    for geom in range(scene.num_geoms):
        rows, cols = np.nonzero(seg == geom)
        out[geom] = (cols.mean() + 0.5, rows.mean() + 0.5) if len(rows) else (np.nan, np.nan)
    return out


def test_projection_matches_torchsim_renderer():
    """The test's pinhole projection agrees with torchsim's camera convention (so the browser check below measures
    the viewer, not the test): a sphere's pixels in ``render`` centre on its projected centre."""
    for ball in ((0.5, 0.0, 0.3), (0.2, -0.5, -0.4)):
        _, scene, state = two_bodies(ball, (-0.6, 0.4, -0.2))
        got = segmentation_centroids(scene, state, 320, 240)[0]
        np.testing.assert_allclose(got, project(ball, 320, 240), atol=0.5)


def test_geom_meshes_have_mujoco_sizes():
    pytest.importorskip("viser", reason="viser not installed (pip install viser)")
    from torchsim.render.viewer import geom_mesh

    cases = {"sphere": ((0.3, 0, 0), (0.3, 0.3, 0.3)), "ellipsoid": ((0.1, 0.2, 0.3), (0.1, 0.2, 0.3)),
             "capsule": ((0.1, 0.4, 0), (0.1, 0.1, 0.5)), "cylinder": ((0.2, 0.3, 0), (0.2, 0.2, 0.3)),
             "box": ((0.1, 0.2, 0.3), (0.1, 0.2, 0.3)), "plane": ((2.0, 3.0, 0.1), (2.0, 3.0, 0.0))}
    for kind, (size, half_extent) in cases.items():
        vertices, faces = geom_mesh(kind, size)
        assert faces.max() < len(vertices)
        np.testing.assert_allclose(np.abs(vertices).max(0), half_extent, rtol=0.02, atol=1e-9, err_msg=kind)
    vertices, _ = geom_mesh("plane", (0, 0, 1), plane_extent=7.0)
    np.testing.assert_allclose(np.abs(vertices).max(0), (7.0, 7.0, 0.0))


def test_viewer_moves_bodies_to_state():
    pytest.importorskip("viser", reason="viser not installed (pip install viser)")
    from torchsim.render.viewer import Viewer

    _, scene, state = two_bodies((0.5, 0.0, 0.3), (-0.6, 0.4, -0.2))
    viewer = Viewer(scene, host="127.0.0.1", port=8790, verbose=False)
    try:
        viewer.update(state)
        np.testing.assert_allclose(viewer.bodies[0].position, (0.5, 0.0, 0.3), atol=1e-9)
        np.testing.assert_allclose(viewer.bodies[1].position, (-0.6, 0.4, -0.2), atol=1e-9)
        _, _, moved = two_bodies((0.1, 0.2, 0.3), (-0.6, 0.4, -0.2))
        viewer.update(moved)
        np.testing.assert_allclose(viewer.bodies[0].position, (0.1, 0.2, 0.3), atol=1e-9)
    finally:
        viewer.close()


MOCAP_TARGET = """
<mujoco>
  <worldbody>
    <body name="ball" pos="0 0 0"><freejoint/><geom type="sphere" size="0.15" rgba="0 0.8 0 1"/></body>
    <body name="target" mocap="true" pos="0 0 1"><geom type="box" size="0.1 0.1 0.1" contype="0" conaffinity="0"/></body>
  </worldbody>
</mujoco>
"""


def test_viewer_moves_mocap_bodies_to_given_poses():
    """A mocap body's frame starts at the model's pose and goes where an update puts it: shared ``(K, 3)`` or env
    ``env``'s row of per-env ``(B, K, 3)`` poses (the System's, as the env's ``set_mocap`` leaves them); an update
    without them leaves it there; a pose of the wrong shape is refused with the shapes it takes."""
    pytest.importorskip("viser", reason="viser not installed (pip install viser)")
    import mujoco

    from torchsim.render.viewer import Viewer

    system = torchsim.load_mjcf(MOCAP_TARGET)
    scene = Scene.build(mujoco.MjModel.from_xml_string(MOCAP_TARGET), system)
    state = torchsim.init(system, system.q0[None].repeat(2, 1), torch.zeros(2, system.nv))
    viewer = Viewer(scene, host="127.0.0.1", port=8791, verbose=False)
    try:
        np.testing.assert_allclose(viewer.mocap[0].position, (0.0, 0.0, 1.0), atol=1e-9)
        turn = (np.cos(0.25), 0.0, 0.0, np.sin(0.25))  # 0.5 rad about z
        viewer.update(state, mocap_pos=torch.tensor([[0.3, -0.2, 0.5]]), mocap_quat=torch.tensor([turn]))
        np.testing.assert_allclose(viewer.mocap[0].position, (0.3, -0.2, 0.5), atol=1e-9)
        np.testing.assert_allclose(viewer.mocap[0].wxyz, turn, atol=1e-9)
        per_env = torch.tensor([[[0.3, -0.2, 0.5]], [[-0.4, 0.1, 0.7]]])
        viewer.update(state, env=1, mocap_pos=per_env)
        np.testing.assert_allclose(viewer.mocap[0].position, (-0.4, 0.1, 0.7), atol=1e-9)
        np.testing.assert_allclose(viewer.mocap[0].wxyz, turn, atol=1e-9)  # quaternion left out: kept
        viewer.update(state)
        np.testing.assert_allclose(viewer.mocap[0].position, (-0.4, 0.1, 0.7), atol=1e-9)
        with pytest.raises(ValueError, match=r"mocap_pos must be \(1, 3\) or \(B, 1, 3\)"):
            viewer.update(state, mocap_pos=torch.zeros(2, 3))
    finally:
        viewer.close()


def test_trajectories_carry_mocap_poses():
    """``play``, ``to_html`` and ``save_html`` take the mocap bodies' poses along a trajectory, ``(T, K, .)`` or
    ``(K, .)`` for every frame: the frame ends where the last pose puts it, and a track of another length is
    refused with the shapes it takes."""
    pytest.importorskip("viser", reason="viser not installed (pip install viser)")
    import mujoco

    from torchsim.render.viewer import Viewer, mocap_track, trajectory

    system = torchsim.load_mjcf(MOCAP_TARGET)
    scene = Scene.build(mujoco.MjModel.from_xml_string(MOCAP_TARGET), system)
    poses = trajectory(system, system.q0[None].repeat(3, 1))
    track = torch.tensor([[[0.0, 0.0, 1.0]], [[0.2, 0.0, 1.0]], [[0.4, -0.1, 0.8]]]), torch.tensor([1.0, 0, 0, 0.5])
    pos, quat = mocap_track((track[0], track[1][None]), 3, 1)
    assert pos.shape == (3, 1, 3) and quat.shape == (3, 1, 4)
    np.testing.assert_allclose(quat[2, 0], np.array([1.0, 0, 0, 0.5]) / np.sqrt(1.25))
    viewer = Viewer(scene, host="127.0.0.1", port=8792, verbose=False)
    try:
        viewer.play(poses, dt=0.0, mocap=(track[0], track[1][None]))
        np.testing.assert_allclose(viewer.mocap[0].position, (0.4, -0.1, 0.8), atol=1e-9)
        np.testing.assert_allclose(viewer.mocap[0].wxyz, quat[2, 0], atol=1e-9)
        moving, still = viewer.to_html(poses, 0.05, mocap=(track[0], track[1][None])), viewer.to_html(poses, 0.05)
        assert moving != still
        np.testing.assert_allclose(viewer.mocap[0].position, (0.4, -0.1, 0.8), atol=1e-9)  # no track: left there
        with pytest.raises(ValueError, match=r"mocap_pos must be \(1, 3\) or \(T, 1, 3\).*T = 3 frames"):
            viewer.play(poses, dt=0.0, mocap=(track[0][:2], track[1][None]))
    finally:
        viewer.close()


def _chromium():
    for name in ("chromium", "chromium-browser", "google-chrome"):
        if shutil.which(name):
            return shutil.which(name)
    return None


def _screenshot(browser, page, width, height, ready):
    """Headless Chromium's screenshot of ``page``, taken after 3 s of the page's virtual time, again after 15 s and
    60 s while ``ready(image)`` is false: on a loaded machine (CI's other pytest worker compiling) the software-GL
    frame can land after a short budget's screenshot. Returns the last image, for the test to judge, and Chromium's
    console lines."""
    from PIL import Image

    shot = page.with_name("shot.png")
    for budget_ms in (3000, 15000, 60000):
        shot.unlink(missing_ok=True)
        # software WebGL (SwiftShader); no sandbox: CI containers run as root or without user namespaces; no
        # background networking: the machine's network is closed and the page needs none; no /dev/shm: a container's
        # is often 64 MiB, too small for the renderer
        cmd = [browser, "--headless", "--no-sandbox", "--hide-scrollbars", "--mute-audio",
               "--enable-unsafe-swiftshader", "--no-first-run", "--disable-background-networking",
               "--disable-component-update", "--disable-sync", "--disable-dev-shm-usage",
               f"--user-data-dir={page.with_name(f'profile{budget_ms}')}", "--enable-logging=stderr", "--v=0",
               f"--window-size={width},{height}", f"--virtual-time-budget={budget_ms}", f"--screenshot={shot}",
               page.as_uri()]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=180, check=False)
        console = "\n".join(line for line in proc.stderr.splitlines() if "CONSOLE" in line or "WebGL" in line)
        assert shot.exists(), f"Chromium wrote no screenshot (budget {budget_ms} ms): {console or proc.stderr[-2000:]}"
        image = np.asarray(Image.open(shot).convert("RGB"))
        assert image.shape[:2] == (height, width)
        if ready(image):
            break
    return image, console


def test_saved_file_in_headless_chromium(tmp_path):
    """Two saved viewer files (the ball moved between them) side by side in one page; headless Chromium's
    screenshot shows each body within a few pixels of its projected position, in both files."""
    pytest.importorskip("viser", reason="viser not installed (pip install viser)")
    browser = _chromium()
    if browser is None:
        pytest.skip("no Chromium (apt-get install chromium) to open the saved viewer file")
    from torchsim.render.viewer import save_html

    cube = (-0.6, 0.4, -0.2)
    balls = [(0.5, 0.0, 0.3), (0.2, -0.5, -0.4)]
    expected = []
    for i, ball in enumerate(balls):
        _, scene, state = two_bodies(ball, cube)
        expected.append(segmentation_centroids(scene, state, VIEW_W, VIEW_H))
        path = save_html(scene, state, tmp_path / f"view{i}.html", eye=EYE, target=TARGET, fovy=FOVY)
        text = path.read_text()
        assert "__VISER_EMBED_DATA__" in text and "<script" in text  # the client and the data in one file
    frames = "".join(f'<iframe src="view{i}.html" style="position:absolute;left:{i * VIEW_W}px;top:0;border:0" '
                     f'width="{VIEW_W}" height="{VIEW_H}"></iframe>' for i in range(2))
    (tmp_path / "both.html").write_text(f"<html><body style='margin:0'>{frames}</body></html>")
    image, console = _screenshot(browser, tmp_path / "both.html", 2 * VIEW_W, VIEW_H,
                                 ready=lambda img: all(centroid(img[:, i * VIEW_W:(i + 1) * VIEW_W], c)[1] > 500
                                                       for i in range(2) for c in (1, 2)))
    seen = {(i, channel): centroid(image[:, i * VIEW_W:(i + 1) * VIEW_W], channel)
            for i in range(2) for channel in (1, 2)}
    report = "\n".join(f"view {i} {('ball', 'cube')[channel - 1]}: {count} pixels, centroid ({col:.2f}, {row:.2f}), "
                       f"torchsim's renderer ({expected[i][channel - 1][0]:.2f}, {expected[i][channel - 1][1]:.2f})"
                       for (i, channel), ((col, row), count) in seen.items())
    for (i, channel), ((col, row), count) in seen.items():   # green ball = geom 0, blue cube = geom 1
        want = expected[i][channel - 1]
        assert count > 500 and abs(col - want[0]) < 2 and abs(row - want[1]) < 2, \
            f"{report}\nChromium's console:\n{console}"
    for i, ball in enumerate(balls):
        view = image[:, i * VIEW_W:(i + 1) * VIEW_W]
        # and the ball's centre, by the pinhole projection of its position
        np.testing.assert_allclose(centroid(view, 1)[0], project(ball, VIEW_W, VIEW_H), atol=2.0)
    # the ball moved by (-0.3, -0.5, -0.7) m between the files: so did its pixels, by the projected amount
    shift = np.subtract(centroid(image[:, VIEW_W:], 1)[0], centroid(image[:, :VIEW_W], 1)[0])
    expected_shift = np.subtract(project(balls[1], VIEW_W, VIEW_H), project(balls[0], VIEW_W, VIEW_H))
    assert np.all(np.abs(shift - expected_shift) < 3) and np.linalg.norm(expected_shift) > 100


# ------------------------------------------------------------------------------------------------ videos (torchsim)
BALL_ON_FLOOR = """
<mujoco>
  <worldbody>
    <geom name="floor" type="plane" size="3 3 0.1" rgba="0.5 0.5 0.5 1"/>
    <body name="ball" pos="0 0 0.3"><freejoint/><geom type="sphere" size="0.2" rgba="0.9 0.1 0.1 1"/></body>
  </worldbody>
</mujoco>
"""


def rolling_ball(frames=6):
    """The model, its System and a trajectory moving the ball 1.5 m along x, 0.3 m above the floor."""
    import mujoco

    model = mujoco.MjModel.from_xml_string(BALL_ON_FLOOR)
    system = torchsim.load_mjcf(BALL_ON_FLOOR)
    qpos = np.zeros((frames, 7))
    qpos[:, 0], qpos[:, 2], qpos[:, 3] = np.linspace(0.0, 1.5, frames), 0.3, 1.0
    return model, system, qpos


def red_centroid(frame):
    rgb = frame.astype(np.int32)
    rows, cols = np.nonzero((rgb[..., 0] > rgb[..., 1] + 60) & (rgb[..., 0] > rgb[..., 2] + 60))
    return cols.mean() + 0.5, rows.mean() + 0.5


def test_video_frames_track_the_body_over_a_checkered_floor():
    """The default camera follows the ball (it stays at the image centre) while the floor's checkerboard slides
    past; a world-fixed look-at camera sees the ball move by its projected displacement."""
    from torchsim.envs.video import render_frames_torchsim

    model, system, qpos = rolling_ball()
    frames = render_frames_torchsim(model, system, qpos, 96, 72, distance=3.0)
    assert len(frames) == len(qpos) and frames[0].shape == (72, 96, 3) and frames[0].dtype == np.uint8
    for frame in frames:
        np.testing.assert_allclose(red_centroid(frame), (48, 36), atol=1.0)
    changed = lambda a, b: (np.abs(a[60:].astype(np.int32) - b[60:]) > 8).mean()  # rows below the ball: floor
    assert changed(frames[1], frames[0]) > 0.05  # the squares moved under the tracked camera
    plain = render_frames_torchsim(model, system, qpos, 96, 72, distance=3.0, checker=0)
    assert changed(plain[1], plain[0]) == 0  # without squares: a still floor
    eye, target = (0.0, -3.0, 0.3), (0.0, 0.0, 0.3)
    fixed = render_frames_torchsim(model, system, qpos, 96, 72, camera=Camera.look_at(eye, target, fovy=FOVY))
    global EYE, TARGET
    saved, (EYE, TARGET) = (EYE, TARGET), (eye, target)
    try:
        for frame, q in zip(fixed, qpos):
            np.testing.assert_allclose(red_centroid(frame), project(q[:3], 96, 72), atol=1.0)
    finally:
        EYE, TARGET = saved


def test_save_video_gif_and_mp4(tmp_path):
    import importlib.util

    from PIL import Image

    from torchsim.envs.video import save_video

    frames = [np.full((31, 41, 3), 8 * i, dtype=np.uint8) for i in range(12)]
    gif = save_video(frames, tmp_path / "a.gif", fps=20)
    with Image.open(gif) as im:
        assert im.n_frames == 12 and im.size == (41, 31) and im.info["duration"] == 50
    if importlib.util.find_spec("imageio_ffmpeg") is None:
        with pytest.warns(UserWarning, match="MP4 needs imageio"):
            out = save_video(frames, tmp_path / "a.mp4", fps=20)
        assert out.suffix == ".gif" and out.exists()
    else:
        import imageio.v2 as imageio

        out = save_video(frames, tmp_path / "a.mp4", fps=20)
        back = imageio.mimread(out)
        assert out.suffix == ".mp4" and len(back) == 12 and back[0].shape == (32, 42, 3)  # padded to even sides
        assert abs(int(back[6][5, 5, 0]) - 48) <= 3


def test_training_video_renders_in_process(tmp_path, monkeypatch):
    """``render_gif`` (a training run's policy.gif) draws with torchsim's renderer in this process: no child
    process is started, and the GIF has one frame per recorded state."""
    import subprocess as sp

    import torchsim.envs
    from torchsim.algos.physics_task import render_gif

    def no_child(*args, **kwargs):
        raise AssertionError("started a child process")

    monkeypatch.setattr(sp, "run", no_child)
    env = torchsim.envs.make("reacher")
    qpos = env.sys.q0[None].repeat(4, 1).double().numpy()
    qpos[:, 0] = np.linspace(0.0, 1.0, 4)
    render_gif("reacher", qpos, env.dt, tmp_path / "policy.gif", width=64, height=48)
    from PIL import Image

    with Image.open(tmp_path / "policy.gif") as im:
        assert im.n_frames == 4 and im.size == (64, 48)
