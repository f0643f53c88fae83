"""Each texel's normal fused with its neighbours' as far as the field is smooth (refine.normal_field)."""

import math

import numpy as np

from ntp_engine.refine.normal_field import fused_normals


def _plane(n: int = 30, spacing: float = 0.001):
    """A flat n x n grid of texels (object space, m) with mesh normal +z."""
    g = np.stack(np.meshgrid(np.arange(n), np.arange(n), indexing="ij"), -1).reshape(-1, 2) * spacing
    return np.concatenate([g, np.zeros((len(g), 1))], 1), np.tile([0.0, 0.0, 1.0], (len(g), 1))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _tilted(tilt_x: np.ndarray, tilt_y: np.ndarray) -> np.ndarray:
    """Unit normals tilted from +z by small angles (radians) toward x and y."""
    return _unit(np.stack([np.tan(tilt_x), np.tan(tilt_y), np.ones_like(tilt_x)], 1))


def _deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip((a * b).sum(1), -1.0, 1.0)))


def test_noise_on_a_smooth_surface_is_averaged_and_its_std_falls():
    position, normal = _plane()
    N = len(position)
    rng = np.random.default_rng(0)
    sigma = math.radians(2.0)  # both tilt axes together
    refined = _tilted(*(rng.normal(0.0, sigma / math.sqrt(2), (2, N))))
    std = np.full(N, sigma)
    fused, fused_std = fused_normals(position, normal, refined, std, np.arange(N))
    before, after = _deg(refined, normal), _deg(fused, normal)
    assert np.median(after) < 0.4 * np.median(before)
    assert (fused_std <= std + 1e-12).all() and np.median(fused_std) < 0.5 * sigma
    np.testing.assert_allclose(np.linalg.norm(fused, axis=1), 1.0)


def test_detail_the_photos_resolve_is_kept():
    # a bevel: a 10 deg tilt on one half of the grid, the photos' noise 0.5 deg
    position, normal = _plane()
    N = len(position)
    rng = np.random.default_rng(1)
    sigma = math.radians(0.5)
    step = np.where(position[:, 0] >= 0.015, math.radians(10.0), 0.0)
    truth = _tilted(step, np.zeros(N))
    refined = _tilted(step + rng.normal(0.0, sigma / math.sqrt(2), N), rng.normal(0.0, sigma / math.sqrt(2), N))
    fused, _ = fused_normals(position, normal, refined, np.full(N, sigma), np.arange(N))
    before, after = _deg(refined, truth), _deg(fused, truth)
    # the texels beside the bevel keep their side's normal, and the noise elsewhere is averaged
    edge = np.abs(position[:, 0] - 0.0145) < 0.0011
    assert after[edge].max() < 1.5 and np.median(after) < 0.6 * np.median(before)


def test_a_texel_its_neighbours_contradict_beyond_the_gate_keeps_its_own():
    position, normal = _plane(n=9)
    N = len(position)
    refined = normal.copy()
    centre = N // 2
    refined[centre] = _tilted(np.array([math.radians(5.0)]), np.zeros(1))[0]
    std = np.full(N, math.radians(0.2))
    fused, fused_std = fused_normals(position, normal, refined, std, np.arange(N))
    np.testing.assert_allclose(fused[centre], refined[centre])
    assert fused_std[centre] == std[centre]


def test_the_mesh_curvature_is_not_smoothed_and_a_lone_texel_keeps_its_normal():
    # on a cylinder of 2 cm radius the refined normals are the mesh's: fusing offsets changes nothing
    theta = np.linspace(0.0, 1.0, 40)
    z = np.linspace(0.0, 0.02, 10)
    tt, zz = np.meshgrid(theta, z, indexing="ij")
    position = np.stack([0.02 * np.cos(tt), 0.02 * np.sin(tt), zz], -1).reshape(-1, 3)
    normal = np.stack([np.cos(tt), np.sin(tt), np.zeros_like(tt)], -1).reshape(-1, 3)
    std = np.full(len(position), math.radians(1.0))
    fused, _ = fused_normals(position, normal, normal, std, np.arange(len(position)))
    assert _deg(fused, normal).max() < 1e-6
    one, one_std = fused_normals(position, normal, normal, std, np.array([3]))
    np.testing.assert_allclose(one[0], normal[3])
    assert one_std[0] == std[3]
