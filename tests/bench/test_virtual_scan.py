from ntp_engine.bench import virtual_scan


def test_seconds_per_photo_and_the_shadow_error_are_reported():
    r = virtual_scan.run(photos=1, scales=(0.05,), shadow_scale=0.05)
    assert r["seconds_per_photo_scale_0.05"] > 0 and r["shadow_pixels"] > 0
    assert 0 <= r["shadow_rel_err_median"] <= r["shadow_rel_err_p99"] <= r["shadow_rel_err_max"]
    # the compiled per-pixel sums against the torch terms on the same photo: float32 rounding apart
    assert r["seconds_per_photo_compiled_sums"] > 0 and r["seconds_per_photo_tensor_sums"] > 0
    assert 0 < r["shading_rel_diff_max"] < 1e-4
