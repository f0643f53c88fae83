"""The folders ntp writes: claimed only when absent, empty or ntp's own; never inside an input; one
run at a time; leftovers of killed runs removed; a result complete only with its report."""

import errno
import json
import multiprocessing
import os
import time

import pytest

from ntp_engine.io import output_folder
from ntp_engine.io.errors import NtpInputError
from ntp_engine.io.output_folder import (
    MARKER,
    check_claimable,
    check_not_inside,
    claim,
    is_complete,
    publish,
    remove_temporaries,
)


def test_check_not_inside(tmp_path):
    scan = tmp_path / "scan"
    scan.mkdir()
    with pytest.raises(NtpInputError, match="is the input folder"):
        check_not_inside(scan / "a" / "..", (scan,))
    for bad in (scan / "result", scan / "a" / ".." / "result"):
        with pytest.raises(NtpInputError, match="is inside the input folder"):
            check_not_inside(bad, (scan,))
    check_not_inside(tmp_path / "scan_result", (scan,))  # a sibling with a common prefix is fine


def test_check_claimable(tmp_path):
    check_claimable(tmp_path / "absent", "result")
    (tmp_path / "empty").mkdir()
    check_claimable(tmp_path / "empty", "result")
    (tmp_path / "file").write_text("x")
    with pytest.raises(NtpInputError, match="is a file, not a folder"):
        check_claimable(tmp_path / "file", "result")
    user = tmp_path / "user"
    user.mkdir()
    (user / "mesh.obj").write_text("mine")
    with pytest.raises(NtpInputError, match="not empty and not an ntp result folder .*'mesh.obj'"):
        check_claimable(user, "result")
    (user / MARKER).write_text(json.dumps({"ntp": "scan"}))
    with pytest.raises(NtpInputError, match="is an ntp scan folder, not a result folder"):
        check_claimable(user, "result")
    check_claimable(user, "scan")
    (user / MARKER).write_text("{truncated")
    with pytest.raises(NtpInputError, match="ntp unknown folder"):
        check_claimable(user, "scan")


def test_claim_marks_locks_and_cleans(tmp_path):
    out = tmp_path / "out"
    with claim(out, "result") as folder:
        assert folder == out and json.loads((out / MARKER).read_text()) == {"ntp": "result"}
        if output_folder.fcntl is not None:
            with pytest.raises(NtpInputError, match="another ntp run is writing"), claim(out, "result"):
                pass
    # leftovers of a killed run: ntp's temporary names go, anything else stays
    (out / "cache" / ".ntp-tmp.traces.ab12cd_9").mkdir(parents=True)
    (out / ".ntp-tmp.diffuse_albedo.k2j4h5g6.exr").write_text("half")
    (out / ".notes").write_text("mine")
    (out / "cache" / ".my.settings").write_text("mine")
    with claim(out, "result"):
        pass
    assert sorted(p.name for p in out.rglob("*")) == [".my.settings", ".notes", MARKER, "cache"]
    assert oct(os.stat(out / MARKER).st_mode & 0o777) == oct(0o666 & ~_umask())


def test_claim_refuses_what_it_cannot_write(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(NtpInputError, match="cannot write here"), claim(tmp_path / "file" / "out", "result"):
        pass


def test_remove_temporaries_leaves_nested_claims_alone(tmp_path):
    (tmp_path / "result" / ".ntp-tmp.fit.abcdefgh").mkdir(parents=True)
    (tmp_path / "result" / MARKER).write_text('{"ntp": "result"}')
    (tmp_path / ".ntp-tmp.relit.zzzzzzzz").mkdir()
    remove_temporaries(tmp_path)
    assert (tmp_path / "result" / ".ntp-tmp.fit.abcdefgh").is_dir()
    assert not (tmp_path / ".ntp-tmp.relit.zzzzzzzz").exists()


def test_publish_writes_the_report_last(tmp_path, monkeypatch):
    out, staging = tmp_path / "out", tmp_path / "out" / ".ntp-tmp.result.abcdefgh"
    (staging / "previews").mkdir(parents=True)
    (out / "previews").mkdir()
    for name in ("a.exr", "b.exr", "previews/a.png"):
        (staging / name).write_text("new")
        (out / name).write_text("old")
    (out / "report.json").write_text("{}")
    (out / "index.html").write_text("the old result's page")
    assert is_complete(out)
    moves = []

    def replace_then_die(src, dst):  # a kill after the second move
        if len(moves) == 2:
            raise KeyboardInterrupt
        moves.append(dst)
        os.rename(src, dst)

    monkeypatch.setattr(output_folder.os, "replace", replace_then_die)
    with pytest.raises(KeyboardInterrupt):
        publish(staging, out, '{"done": true}')
    assert not is_complete(out)  # two new files beside old ones: not marked complete
    monkeypatch.undo()
    (staging / "a.exr").write_text("new")
    (staging / "b.exr").write_text("new")
    publish(staging, out, '{"done": true}')
    assert is_complete(out) and not staging.exists()
    assert {p.name: p.read_text() for p in out.rglob("*.*")} == {
        "a.exr": "new",
        "b.exr": "new",
        "a.png": "new",
        "report.json": '{"done": true}',
    }


def _umask() -> int:
    m = os.umask(0)
    os.umask(m)
    return m


def _claim_at_once(folder: str, start, held) -> None:
    start.wait()
    try:
        with claim(folder, "result"):
            held.put(1)
            time.sleep(0.1)  # hold it while the other one tries
    except NtpInputError:
        held.put(0)


def test_two_runs_claiming_a_fresh_folder_at_once_never_both_hold_it(tmp_path):
    """The marker was written by rename: a second run replaced the marker the first had locked and
    locked its own file (both held "the" lock 42 times in 100). Linked into place, it is one file."""
    ctx = multiprocessing.get_context("fork")
    both = 0
    for i in range(40):
        start, held = ctx.Barrier(2), ctx.Queue()
        runs = [ctx.Process(target=_claim_at_once, args=(str(tmp_path / str(i)), start, held)) for _ in range(2)]
        for r in runs:
            r.start()
        for r in runs:
            r.join()
        both += held.get() + held.get() == 2
        assert json.loads((tmp_path / str(i) / MARKER).read_text()) == {"ntp": "result"}
    assert both == 0


def test_the_marker_is_made_without_hard_links_too(tmp_path, monkeypatch):
    def no_links(src, dst):
        raise OSError(errno.EPERM, "Operation not permitted")

    monkeypatch.setattr(output_folder.os, "link", no_links)
    with claim(tmp_path / "fat", "result"):
        assert json.loads((tmp_path / "fat" / MARKER).read_text()) == {"ntp": "result"}
    assert sorted(p.name for p in (tmp_path / "fat").iterdir()) == [MARKER]  # no temporary left
