import numpy as np
import pytest

from ntp_engine.io.errors import NtpInputError
from ntp_engine.io.images import write_exr
from ntp_engine.io.maps import SVBRDFMaps, bilinear, fill_missing, texel_uv, uv_to_pixel


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
