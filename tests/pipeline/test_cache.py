"""``ntp reconstruct`` end to end on virtual scans: SfM + alignment, given poses, caching/resume,
photo selection, bad input."""

import json

import numpy as np
import pytest

from ntp_engine.pipeline.cache import StageCache


def test_stage_cache_keys_and_failures(tmp_path):
    cache = StageCache(tmp_path)
    calls = []

    def write(d):
        calls.append(1)
        (d / "x.txt").write_text("1")

    a, h1 = cache.get("s", {"k": 1}, write)
    b, h2 = cache.get("s", {"k": 1}, write)
    assert a == b and h1 == h2 and len(calls) == 1 and cache.hits == ["s"]
    _, h3 = cache.get("s", {"k": 2}, write)
    assert h3 != h1 and len(calls) == 2

    def fail(d):
        (d / "partial").write_text("half")
        raise RuntimeError("stop")

    with pytest.raises(RuntimeError):
        cache.get("s", {"k": 3}, fail)
    assert (tmp_path / "s" / "x.txt").is_file() and not list(tmp_path.glob(".ntp-tmp.*"))  # old result intact
    assert json.loads((tmp_path / "s" / "key.json").read_text())["key"] == {"k": 2}


def test_cache_keys_see_every_element_of_an_array():
    from ntp_engine.pipeline.cache import digest

    a = np.zeros((512, 3))
    b = a.copy()
    b[256, 1] = 1e-3  # in the middle, where numpy's repr would write "..."
    assert digest({"pattern": a}) != digest({"pattern": b}) and digest({"pattern": a}) == digest({"pattern": a.copy()})
