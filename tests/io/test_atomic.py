import os
import stat

import pytest

from ntp_engine.io.atomic import atomic_path, write_text_atomic


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    target = tmp_path / "report.json"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("interrupted")
    assert target.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["report.json"]


def test_a_finished_file_follows_the_umask(tmp_path):
    old = os.umask(0o022)
    try:
        write_text_atomic(tmp_path / "sub" / "a.txt", "done")
    finally:
        os.umask(old)
    path = tmp_path / "sub" / "a.txt"
    assert path.read_text() == "done" and stat.S_IMODE(path.stat().st_mode) == 0o644


def test_temp_dir_and_umask_mode(tmp_path):
    from ntp_engine.io.atomic import TEMP_PREFIX, temp_dir, umask_mode

    d = temp_dir(tmp_path / "new", "traces")
    assert d.is_dir() and d.parent == tmp_path / "new" and d.name.startswith(TEMP_PREFIX + "traces.")
    mask = os.umask(0o027)
    try:
        assert umask_mode(0o666) == 0o640 and umask_mode(0o777) == 0o750
    finally:
        os.umask(mask)


def test_a_failed_rename_names_the_target_not_the_temporary(tmp_path):
    (tmp_path / "taken").mkdir()
    with pytest.raises(IsADirectoryError) as err, atomic_path(tmp_path / "taken") as tmp:
        tmp.write_text("x")
    assert err.value.filename == str(tmp_path / "taken") and list(tmp_path.iterdir()) == [tmp_path / "taken"]
