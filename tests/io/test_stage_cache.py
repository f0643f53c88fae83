"""``ntp reconstruct`` end to end on virtual scans: SfM + alignment, given poses, caching/resume,
photo selection, bad input."""

import json

import numpy as np
import pytest

from ntp_engine.io.stage_cache import StageCache


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
    from ntp_engine.io.stage_cache import digest

    a = np.zeros((512, 3))
    b = a.copy()
    b[256, 1] = 1e-3  # in the middle, where numpy's repr would write "..."
    assert digest({"pattern": a}) != digest({"pattern": b}) and digest({"pattern": a}) == digest({"pattern": a.copy()})


def test_content_keys_follow_bytes_not_times_or_places(tmp_path):
    import os

    from ntp_engine.io.stage_cache import content_digest, content_key, file_digest

    a = tmp_path / "a.png"
    a.write_bytes(b"pixels")
    key = content_key([a])
    os.utime(a, (1, 1))  # touched: same key
    b = tmp_path / "elsewhere" / "a.png"
    b.parent.mkdir()
    b.write_bytes(b"pixels")  # copied: same key
    assert content_key([a]) == key == content_key([b]) and key[0][0] == "a.png"
    a.write_bytes(b"pixelz")
    assert content_digest([a]) != content_digest([b])
    assert file_digest(tmp_path / "missing.png").startswith("unreadable: ")


def test_a_damaged_entry_is_reported_and_recomputed(tmp_path, capsys):
    cache, calls = StageCache(tmp_path), []

    def write(d):
        calls.append(1)
        (d / "x.npz").write_bytes(b"0123456789")

    folder, _ = cache.get("fit", {"k": 1}, write)
    (folder / "x.npz").write_bytes(b"01234")  # truncated
    cache.get("fit", {"k": 1}, write)
    err = capsys.readouterr().err
    assert len(calls) == 2 and cache.recomputed == ["fit"] and err.count("\n") == 1
    assert "fit/x.npz: cache entry damaged" in err and (folder / "x.npz").read_bytes() == b"0123456789"
    (folder / "key.json").write_text('{"digest": ')  # unreadable stamp
    cache.get("fit", {"k": 1}, write)
    assert len(calls) == 3 and "key.json: cache entry damaged" in capsys.readouterr().err
    cache.get("fit", {"k": 1}, write)
    assert len(calls) == 3 and cache.hits == ["fit"]


def test_a_failed_write_names_the_stage_folder(tmp_path):
    import errno

    def full(d):
        raise OSError(errno.ENOSPC, "No space left on device", str(d / "traces.npz"))

    with pytest.raises(OSError) as err:
        StageCache(tmp_path).get("traces", {}, full)
    assert err.value.filename == str(tmp_path / "traces" / "traces.npz") and not list(tmp_path.iterdir())


def _package(root, name, files):
    for rel, text in files.items():
        (root / name / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / name / rel).write_text(text)


def test_the_code_version_follows_imports_within_the_package_and_ignores_comments_and_docstrings(tmp_path, monkeypatch):
    from ntp_engine.io import stage_cache

    name = f"pkgv_{tmp_path.name.replace('-', '_')}"
    files = {
        "__init__.py": "",
        "a.py": "from .sub import b\nimport json\n\ndef f():\n    return b.g()\n",
        "sub/__init__.py": '"""The sub package."""\n',
        "sub/b.py": '"""b."""\n\ndef g():\n    return 1  # one\n',
        "c.py": "X = 1\n",
    }
    _package(tmp_path, name, files)
    monkeypatch.syspath_prepend(str(tmp_path))

    def version():
        stage_cache._module_code.cache_clear()
        return stage_cache.code_version([f"{name}.a"])

    v0 = version()
    _package(tmp_path, name, {"sub/b.py": '"""b, reworded."""\n\ndef g():\n    return 1  # a comment changed\n'})
    assert version() == v0  # comments and docstrings are not code
    _package(tmp_path, name, {"c.py": "X = 2\n"})
    assert version() == v0  # a module a does not import
    _package(tmp_path, name, {"sub/b.py": "def g():\n    return 2\n"})
    v1 = version()
    assert v1 != v0  # imported through a subpackage, transitively
    _package(tmp_path, name, {"a.py": "from .sub import b\nimport json\n\ndef f():\n    return b.g() + 1\n"})
    assert version() not in (v0, v1)
    stage_cache._module_code.cache_clear()
