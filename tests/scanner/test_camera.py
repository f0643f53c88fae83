import numpy as np
import torch

from ntp_engine.scanner import camera
from ntp_engine.scanner.device_file import load_scanner


def test_response_round_trip_and_clipping():
    d = load_scanner()
    x = torch.linspace(0, 1, 101, dtype=torch.float64)
    for response in ("linear", "gamma", "srgb"):
        d.response = response
        torch.testing.assert_close(camera.decode(d, camera.encode(d, x)), x)
    d.response = "linear"
    assert float(camera.encode(d, torch.tensor(2.0))) == 255.0


def test_projection_matches_colmap_opencv_model():
    import pycolmap

    d = load_scanner()
    d.distortion = np.array([-0.1, 0.02, 0.001, -0.002, 0.0])
    pts = np.array([[0.1, 0.05, 0.3], [-0.05, 0.02, 0.31], [0.0, 0.0, 0.4]])
    cam = pycolmap.Camera(
        model="OPENCV",
        width=d.width,
        height=d.height,
        params=[d.K[0, 0], d.K[1, 1], d.K[0, 2], d.K[1, 2], *d.distortion[:4]],
    )
    ours = camera.project(d, torch.tensor(pts)).numpy()
    np.testing.assert_allclose(ours, cam.img_from_cam(pts), atol=1e-6)
    assert torch.isnan(camera.project(d, torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64))).all()


def test_projection_jacobian_matches_central_differences():
    d = load_scanner()
    d.distortion = np.array([-0.1, 0.02, 0.001, -0.002, 0.01])
    pts = torch.tensor([[0.1, 0.05, 0.3], [-0.05, 0.02, 0.31], [0.0, 0.0, 0.4]], dtype=torch.float64)
    J = camera.project_jacobian(d, pts)
    h = 1e-7
    for k in range(3):
        e = torch.zeros(3, dtype=torch.float64)
        e[k] = h
        numeric = (camera.project(d, pts + e) - camera.project(d, pts - e)) / (2 * h)
        torch.testing.assert_close(J[..., k], numeric, rtol=1e-6, atol=1e-4)
    assert torch.isnan(camera.project_jacobian(d, torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64))).all()


def test_pixel_rays_invert_the_projection_with_distortion():
    d = camera.resampled(load_scanner(), 0.05)
    d.distortion = np.array([-0.1, 0.02, 0.001, -0.002, 0.0])
    rays = camera.pixel_rays(d)  # (H, W, 3) unit
    np.testing.assert_allclose(np.linalg.norm(rays, axis=-1), 1.0, atol=1e-12)
    px = camera.project(d, torch.as_tensor(rays.reshape(-1, 3))).numpy()
    rows, cols = np.meshgrid(np.arange(d.height), np.arange(d.width), indexing="ij")
    np.testing.assert_allclose(px, np.stack([cols, rows], -1).reshape(-1, 2), atol=1e-6)
    # any pixel coordinates, a skewed sensor included
    d.K = d.K.copy()
    d.K[0, 1] = 0.7
    at = np.random.default_rng(0).uniform(0, [d.width - 1, d.height - 1], (50, 2))
    dirs = camera.pixel_directions(d, at[:, 0], at[:, 1])
    np.testing.assert_allclose(camera.project(d, torch.as_tensor(0.3 * dirs)).numpy(), at, atol=1e-6)


def test_valid_codes_need_every_channel_in_range():
    codes = np.array([[32.0, 100.0, 224.0], [31.9, 100.0, 100.0], [100.0, 224.1, 100.0]])
    assert camera.code_is_valid(codes).tolist() == [True, False, False]
    assert camera.code_is_valid(torch.as_tensor(codes)).tolist() == [True, False, False]


def test_look_at_aims_the_optical_axis_and_keeps_the_horizon_level():
    pos, target = np.array([0.3, -0.2, 0.25]), np.array([0.0, 0.01, 0.03])
    pose = camera.look_at(pos, target)
    R, t = pose[:3, :3], pose[:3, 3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(R @ target + t, [0.0, 0.0, np.linalg.norm(target - pos)], atol=1e-12)
    assert abs(R[0, 2]) < 1e-12  # the camera's x axis is horizontal
    assert R[1, 2] < 0  # image down (y) points down in the world


def test_resampled_keeps_the_field_of_view():
    d = load_scanner()
    half = camera.resampled(d, 0.5)
    assert (half.width, half.height) == (d.width // 2, d.height // 2)
    x = torch.tensor([[0.02, -0.01, 0.3]], dtype=torch.float64)
    full_px, half_px = camera.project(d, x).numpy(), camera.project(half, x).numpy()
    np.testing.assert_allclose((half_px + 0.5) / 0.5 - 0.5, full_px, atol=1e-9)  # same ray, scaled pixel grid


def test_in_image_keeps_the_border_pixel_centres_and_drops_what_lies_behind():
    s = load_scanner()
    w, h = s.width - 1, s.height - 1
    px = np.array([[0, 0], [w, h], [-0.01, 5], [5, h + 0.01], [w + 1, 0], [np.nan, np.nan]], float)
    assert camera.in_image(s, px).tolist() == [True, True, False, False, False, False]
    behind = camera.project(s, torch.tensor([[0.0, 0.0, -0.2]], dtype=torch.float64)).numpy()
    assert not camera.in_image(s, behind).any()
