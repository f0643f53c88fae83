from ntp_engine.bench import physics


def test_throughput_is_measured_for_both_precisions():
    r = physics.run(brdf_batch=1 << 12, lumitexel_batch=8, point_batch=16)
    assert all(
        r[dt][k] > 0
        for dt in ("float32", "float64")
        for k in ("brdf_evals_per_s", "lumitexels_per_s", "measurements_per_s")
    )
