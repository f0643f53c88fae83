import numpy as np
import pytest

from ntp_engine.io.errors import NtpInputError
from ntp_engine.io.images import write_exr
from ntp_engine.io.maps import SVBRDFMaps, axis_weight, bilinear, consistent_axes, fill_missing, texel_uv, uv_to_pixel


def _maps(h=4, w=6):
    rng = np.random.default_rng(0)
    n = np.zeros((h, w, 3))
    n[..., 2] = 1
    t = np.zeros((h, w, 3))
    t[..., 0] = 1
    return SVBRDFMaps(rng.random((h, w, 3)), rng.random((h, w, 3)), n, t, 0.1 + 0.1 * rng.random((h, w, 2)))


def test_save_load_and_texel_centres_sample_exactly(tmp_path):
    m = _maps()
    m.save(tmp_path)
    back = SVBRDFMaps.load(tmp_path)
    np.testing.assert_allclose(back.roughness, m.roughness, rtol=1e-6)
    s = back.sample(texel_uv(m.shape).reshape(-1, 2))
    np.testing.assert_allclose(s["diffuse_albedo"], m.diffuse_albedo.reshape(-1, 3), rtol=1e-6)
    r, c = uv_to_pixel(np.array([[0.5 / 6, 1 - 0.5 / 4]]), (4, 6))
    assert (r[0], c[0]) == pytest.approx((0.0, 0.0))  # row 0 is the top: v = 1


def test_bilinear_is_linear_between_centres_and_fill_takes_the_nearest():
    img = np.arange(4.0).reshape(1, 4, 1)
    np.testing.assert_allclose(bilinear(img, np.array([[0.5, 0.5]])), [[1.5]])
    known = np.array([[True, False, False, True]])
    np.testing.assert_allclose(fill_missing(img, known)[0, :, 0], [0, 0, 3, 3])


def test_bad_map_folders_name_the_file(tmp_path):
    _maps().save(tmp_path)
    write_exr(tmp_path / "normal.exr", np.full((4, 6, 3), np.nan))
    with pytest.raises(NtpInputError, match="normal.exr: map contains NaN"):
        SVBRDFMaps.load(tmp_path)
    write_exr(tmp_path / "normal.exr", np.zeros((5, 6, 3)))
    with pytest.raises(NtpInputError, match="normal.exr: size"):
        SVBRDFMaps.load(tmp_path)
    _maps().save(tmp_path)
    (tmp_path / "tangent.exr").unlink()
    with pytest.raises(NtpInputError, match="tangent.exr: map file missing"):
        SVBRDFMaps.load(tmp_path)


def test_bilinear_samples_skip_the_pixels_they_are_told_not_to_read():
    from ntp_engine.io.maps import bilinear_pixels

    rng = np.random.default_rng(0)
    img = rng.uniform(0, 1, (6, 7, 3))
    r, c = rng.uniform(0, 5, 40), rng.uniform(0, 6, 40)
    plain = bilinear_pixels(img, r, c)
    np.testing.assert_array_equal(bilinear_pixels(img, r, c, np.ones((40, 4), bool)), plain)
    taps = rng.uniform(size=(40, 4)) < 0.6
    taps[np.arange(40), rng.integers(0, 4, 40)] = True  # each sample reads one pixel at least
    r0, c0 = np.floor(r).astype(int), np.floor(c).astype(int)
    corners = [(r0, c0), (r0, c0 + 1), (r0 + 1, c0), (r0 + 1, c0 + 1)]  # r0c0, r0c1, r1c0, r1c1
    got = np.empty_like(plain)
    for i in range(40):  # a skipped pixel is never read: poisoned, one sample at a time
        poisoned = img.copy()
        for k, (rows, cols) in enumerate(corners):
            if not taps[i, k]:
                poisoned[rows[i], cols[i]] = 1e9  # read at any weight (>= 1e-6), it would show
        got[i] = bilinear_pixels(poisoned, r[i : i + 1], c[i : i + 1], taps[i : i + 1])[0]
    # the reference: the bilinear weights of the pixels read, normalised
    fr, fc = r - r0, c - c0
    w = np.stack([(1 - fr) * (1 - fc), (1 - fr) * fc, fr * (1 - fc), fr * fc], 1)
    w = np.maximum(w, 1e-6) * taps
    ref = sum(w[:, k, None] * img[rows, cols] for k, (rows, cols) in enumerate(corners)) / w.sum(1, keepdims=True)
    np.testing.assert_allclose(got, ref, rtol=1e-12)
    flat = np.full((6, 7, 1), 0.25)  # weights still sum to 1
    np.testing.assert_allclose(bilinear_pixels(flat, r, c, taps), 0.25, rtol=1e-12)


def test_bilinear_weights_are_the_samples_own():
    """The weights of ``bilinear_corners``' four pixels reproduce a bilinear sample and sum to 1."""
    from ntp_engine.io.maps import bilinear_corners, bilinear_pixels, bilinear_weights

    rng = np.random.default_rng(3)
    img = rng.random((6, 7, 2))
    r, c = rng.uniform(0, 5, 30), rng.uniform(0, 6, 30)
    rows, cols, fr, fc = bilinear_corners(6, 7, r, c)
    w = bilinear_weights(fr, fc)
    assert w.shape == (30, 4) and (w >= 0).all()
    np.testing.assert_allclose(w.sum(1), 1.0, rtol=1e-12)
    np.testing.assert_allclose((w[..., None] * img[rows, cols]).sum(1), bilinear_pixels(img, r, c), rtol=1e-12)


def _axes(angle: np.ndarray) -> np.ndarray:
    return np.stack([np.cos(angle), np.sin(angle), np.zeros_like(angle)], -1)


def _opposed(axes: np.ndarray) -> int:
    """Neighbouring texel pairs whose axes point opposite ways."""
    return int(((axes[:, 1:] * axes[:, :-1]).sum(-1) < 0).sum() + ((axes[1:] * axes[:-1]).sum(-1) < 0).sum())


def test_axis_weight_is_the_lobes_anisotropy():
    alpha = np.array([[0.2, 0.2], [0.1, 0.4], [0.4, 0.1]])
    assert np.allclose(axis_weight(alpha), [0.0, 0.75, 0.75])  # either order
    assert np.isfinite(axis_weight(np.zeros((1, 2)))).all()  # no NaN where nothing was fitted


def test_consistent_axes_sign_a_field_so_filtering_keeps_it():
    rng = np.random.default_rng(3)
    y, x = np.mgrid[0:24, 0:32]
    smooth = _axes(0.08 * x + 0.05 * y + 0.3 * np.sin(0.2 * y))  # turns ~100 deg over the map
    signs = rng.choice([-1.0, 1.0], (24, 32, 1))
    out = consistent_axes(smooth * signs)
    assert _opposed(smooth * signs) > 300 and _opposed(out) == 0
    np.testing.assert_allclose(np.abs((out * smooth).sum(-1)), 1.0)  # each only negated, or kept
    np.testing.assert_array_equal(out[0, 0], (smooth * signs)[0, 0])  # the root keeps its sign
    midway = bilinear(out, np.array([[1.0 / 32, 1 - 1.5 / 24]]))  # between texels (0..1, 0..1)
    assert np.linalg.norm(midway) > 0.99  # opposite neighbours would have cancelled
    # around a point an axis field turns by 180 deg: no signing is consistent, a few pairs disagree
    vortex = _axes(0.5 * np.arctan2(y - 11.5, x - 15.5)) * signs
    assert _opposed(consistent_axes(vortex)) <= 24
    # texels whose axes do not matter (weight 0, random axes) do not break their neighbours' signing
    noise = rng.uniform(0, np.pi, (24, 32))
    matters = rng.uniform(size=(24, 32)) < 0.7
    mixed = np.where(matters[..., None], smooth * signs, _axes(noise))
    out = consistent_axes(mixed, matters.astype(float))
    both = matters[:, 1:] & matters[:, :-1]
    assert ((out[:, 1:] * out[:, :-1]).sum(-1)[both] < 0).sum() == 0
    assert consistent_axes(_axes(np.zeros((1, 1)))).shape == (1, 1, 3)
