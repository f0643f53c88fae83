from ntp_engine.bench import stability


def test_a_small_run_covers_every_case_and_finds_nothing_non_finite(tmp_path):
    r = stability.run(samples=40_000, json_path=tmp_path / "s.json")
    assert r["samples"] == 40_000 and r["nonfinite"] == 0 and r["total"]["max_rel_err"] < 1e-4
    assert all(case["samples"] > 0 for case in r["cases"].values()) and (tmp_path / "s.json").is_file()
