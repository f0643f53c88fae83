from ntp_engine.bench import fit


def test_batched_fitter_against_the_baseline_on_a_few_texels():
    r = fit.run(texels=64, baseline_texels=2)
    for kind in ("exact", "noisy"):
        assert r[kind]["batched"]["texels_per_s"] > 0 and r[kind]["baseline"]["texels_per_s"] > 0
    assert r["exact"]["batched"]["lumitexel_log_rmse"] < 1e-3  # exact lumitexels are fitted exactly
    whole = r["whole_fit"]  # the stage as the pipeline runs it: every part timed, parts within the total
    assert whole["texels"] == 64 and whole["texels_per_s"] > 0
    assert all(whole["seconds"][k] > 0 for k in ("network", "geometry", "albedo"))
    assert sum(whole["share"].values()) <= 1.0 + 1e-6
    sb = whole["specular_basis"]  # the shipped model's compressed head against its full layer
    assert sb["rank"] < 1024 and sb["seconds"]["exact"] > 0 and sb["seconds"]["compressed"] > 0
    assert 0 < sb["log1p_error_max"] < 0.05
