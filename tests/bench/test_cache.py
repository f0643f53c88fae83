from ntp_engine.bench import cache


def test_hashing_is_measured_against_the_stat_key(tmp_path):
    r = cache.run(photos=3, scale=0.1, big_mb=8, json_path=tmp_path / "c.json")
    s = r["seconds"]
    assert r["photo_size"] == [245, 205] and r["mb_per_photo"] > 0.05 and (tmp_path / "c.json").is_file()
    assert 0 < s["stat (old key)"] < s["sha256, 1 thread"] and r["checksum_gb_per_s"] > 0
