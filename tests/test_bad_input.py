"""The bad-input corpus: every way a user's input, output folder or run can go wrong, run through the
``ntp`` command line as a user runs it. Each case asserts the exit code, a one-line message naming
the file, inputs unchanged (checksums before/after) and a previous good result surviving (or, for
damage ntp repairs, the same result as before). docs/pipeline.md lists the messages."""

from __future__ import annotations

import hashlib
import json
import os
import resource
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from ntp_engine import cli
from ntp_engine.io.images import read_image, write_png
from ntp_engine.io.mesh import Mesh, load_mesh, save_obj
from ntp_engine.io.output_folder import claim, is_complete
from ntp_engine.learn import models
from ntp_engine.scanner.board import board_for_paper
from ntp_engine.scanner.device_file import DEFAULT_DEVICE

RES = "16"


def checksums(folder: Path, skip: tuple[str, ...] = ()) -> dict[str, str]:
    """SHA-256 of every file under ``folder`` (paths relative), leaving out top-level ``skip``."""
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.relative_to(folder).parts[0] not in skip
    }


def outputs(out: Path) -> dict[str, str]:
    """The result's outputs (not the cache, not the report with its timings)."""
    return checksums(out, skip=("cache", "report.json"))


def reconstruct_argv(scan: Path, out: Path, *extra: str) -> list[str]:
    poses = scan / "ground_truth" / "poses.json"
    return ["reconstruct", str(scan), "--out", str(out), "--resolution", RES, "--poses", str(poses), "--quiet", *extra]


@pytest.fixture(scope="module")
def good(scan24, tmp_path_factory):
    """A copy of the 24-photo scan (fresh file times) and a good result of it."""
    root = tmp_path_factory.mktemp("corpus")
    scan, out = root / "scan", root / "good"
    shutil.copytree(scan24, scan, copy_function=shutil.copyfile)
    assert cli.main(reconstruct_argv(scan, out)) == 0
    return scan, out


@pytest.fixture
def copies(good, tmp_path):
    """Private copies of the scan and of the good result for one case."""
    scan, out = tmp_path / "scan", tmp_path / "out"
    shutil.copytree(good[0], scan, copy_function=shutil.copyfile)
    shutil.copytree(good[1], out, copy_function=shutil.copyfile)
    return scan, out


# ------------------------------------------------------------------------------ the refusals
@dataclass(frozen=True)
class Case:
    """Break something (``setup(scan, out, tmp) -> argv``); expect exit ``code``, a last stderr line
    containing ``message`` and the name ``names`` (a file or option)."""

    setup: Callable[[Path, Path, Path], list[str]]
    message: str
    names: str
    code: int = 2


def _write(name: str, data: bytes | None) -> Callable[[Path, Path, Path], list[str]]:
    """Replace (or with None delete) the scan's file ``name``."""

    def setup(scan, out, tmp):
        if data is None:
            (scan / name).unlink()
        else:
            (scan / name).write_bytes(data)
        return reconstruct_argv(scan, out)

    return setup


def _toml(text: bytes) -> Callable[[Path, Path, Path], list[str]]:
    return _write("scan.toml", text)


def _board(data: bytes | None) -> Callable[[Path, Path, Path], list[str]]:
    """scan.toml names a marker board layout ``board.json`` holding ``data`` (None: no such file)."""

    def setup(scan, out, tmp):
        toml = scan / "scan.toml"
        toml.write_text(toml.read_text() + '\nboard = "board.json"\n')
        if data is not None:
            (scan / "board.json").write_bytes(data)
        return reconstruct_argv(scan, out)

    return setup


def _mesh(change: Callable[[Mesh], Mesh]) -> Callable[[Path, Path, Path], list[str]]:
    def setup(scan, out, tmp):
        save_obj(scan / "mesh.obj", change(load_mesh(scan / "mesh.obj")))
        return reconstruct_argv(scan, out)

    return setup


def _moved(m: Mesh, scale: float = 1.0, shift: float = 0.0) -> Mesh:
    return Mesh(m.vertices * scale + np.array([shift, 0, 0]), m.faces, m.uv, m.normals)


def _photos(keep: int | None = None, truncate: bool = False) -> Callable[[Path, Path, Path], list[str]]:
    def setup(scan, out, tmp):
        for i, p in enumerate(sorted((scan / "photos").iterdir())):
            if keep is not None and i >= keep:
                p.unlink()
            elif truncate:
                p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
        return reconstruct_argv(scan, out)

    return setup


def _poses(text: Callable[[dict], bytes]) -> Callable[[Path, Path, Path], list[str]]:
    def setup(scan, out, tmp):
        poses = json.loads((scan / "ground_truth" / "poses.json").read_text())
        (tmp / "poses.json").write_bytes(text(poses))
        return reconstruct_argv(scan, out)[:-3] + ["--poses", str(tmp / "poses.json"), "--quiet"]

    return setup


def _not_rigid(poses: dict) -> bytes:
    first = next(iter(poses))
    poses[first] = (np.array(poses[first]) * np.diag([2, 1, 1, 1])).tolist()
    return json.dumps(poses).encode()


def _device_file(text: bytes) -> Callable[[Path, Path, Path], list[str]]:
    def setup(scan, out, tmp):
        (tmp / "broken.toml").write_bytes(text)
        return reconstruct_argv(scan, out, "--device", str(tmp / "broken.toml"))

    return setup


def _damaged_model(scan, out, tmp):
    folder = tmp / "model"
    shutil.copytree(models.resolve(None), folder)
    (folder / "model.pt").write_bytes((folder / "model.pt").read_bytes()[:1000])
    return reconstruct_argv(scan, out, "--model", str(folder))


def _out(make: Callable[[Path, Path], Path], command: str = "reconstruct") -> Callable[[Path, Path, Path], list[str]]:
    def setup(scan, out, tmp):
        target = make(scan, tmp)
        if command == "reconstruct":
            return reconstruct_argv(scan, target)
        if command == "register":
            return ["register", str(scan), "--out", str(target), "--quiet"]
        if command == "virtual-scan":
            return ["virtual-scan", "--out", str(target), "--views", "2", "--scale", "0.05", "--quiet"]
        return ["demo", "--out", str(target), "--views", "3", "--scale", "0.05", "--resolution", "8", "--quiet"]

    return setup


def _a_file(scan: Path, tmp: Path) -> Path:
    (tmp / "result.txt").write_text("my notes")
    return tmp / "result.txt"


def _user_folder(scan: Path, tmp: Path) -> Path:
    (tmp / "mine").mkdir()
    (tmp / "mine" / "mesh.obj").write_text("my mesh")
    (tmp / "mine" / "report.json").write_text("{}")
    return tmp / "mine"


def _users_atlas(scan: Path, tmp: Path) -> Path:
    (tmp / "mine" / "atlas").mkdir(parents=True)
    (tmp / "mine" / "atlas" / "notes.txt").write_text("my notes")
    return tmp / "mine"


def _cache_link(target: Callable[[Path, Path], Path]) -> Callable[[Path, Path, Path], list[str]]:
    """The result's cache replaced by a link to ``target(scan, tmp)``: ntp deletes inside its cache,
    so it must never follow the link into a folder that is not an ntp cache."""

    def setup(scan, out, tmp):
        shutil.rmtree(out / "cache")
        (out / "cache").symlink_to(target(scan, tmp), target_is_directory=True)
        return reconstruct_argv(scan, out)

    return setup


CASES = {
    "no_scan_toml": Case(_write("scan.toml", None), "no scan.toml", "scan.toml"),
    "scan_toml_not_toml": Case(_toml(b'mesh = "mesh.obj\n'), "not valid TOML", "scan.toml"),
    "scan_toml_not_utf8": Case(_toml(b'mesh = "m\xe9sh.obj"\n'), "not UTF-8 text", "scan.toml"),
    "scan_toml_without_mesh": Case(
        _toml(b'photos = "photos"\ndevice = "device.toml"\n'), "key 'mesh' missing", "scan.toml"
    ),
    "scan_toml_support_light_not_bool": Case(
        _toml(b'mesh = "mesh.obj"\nphotos = "photos"\ndevice = "device.toml"\nsupport_light = "yes"\n'),
        "key 'support_light': expected true or false",
        "scan.toml",
    ),
    "scan_toml_support_light_without_support": Case(
        _toml(
            b'mesh = "mesh.obj"\nphotos = "photos"\ndevice = "device.toml"\n'
            b"support_plane = false\nsupport_light = true\n"
        ),
        "needs a support",
        "scan.toml",
    ),
    "scan_toml_mesh_accuracy_negative": Case(
        _toml(b'mesh = "mesh.obj"\nphotos = "photos"\ndevice = "device.toml"\nmesh_accuracy_mm = -0.3\n'),
        "key 'mesh_accuracy_mm': expected the mesh's accuracy in millimetres",
        "scan.toml",
    ),
    "scan_toml_mesh_accuracy_not_a_number": Case(
        _toml(b'mesh = "mesh.obj"\nphotos = "photos"\ndevice = "device.toml"\nmesh_accuracy_mm = "0.3 mm"\n'),
        "key 'mesh_accuracy_mm': expected the mesh's accuracy in millimetres",
        "scan.toml",
    ),
    "mesh_missing": Case(_write("mesh.obj", None), "does not exist", "mesh.obj"),
    "mesh_garbage": Case(_write("mesh.obj", b"\x00\xffnot a mesh"), "mesh", "mesh.obj"),
    "mesh_in_millimetres": Case(_mesh(lambda m: _moved(m, scale=1000)), "is it in millimetres?", "mesh.obj"),
    "mesh_in_centimetres": Case(_mesh(lambda m: _moved(m, scale=100)), "is it in centimetres?", "mesh.obj"),
    "mesh_one_metre_away": Case(_mesh(lambda m: _moved(m, shift=1.0)), "posed photos see this mesh", "mesh.obj"),
    "device_not_utf8": Case(_device_file(b'name = "caf\xe9"\n'), "not UTF-8 text", "broken.toml"),
    "device_bad_value": Case(_device_file(b'name = "x"\n[camera]\nwidth = "wide"\n'), "camera.width", "broken.toml"),
    "photos_all_truncated": Case(_photos(truncate=True), "only 0 sharp, readable photos", "photos"),
    "photos_two": Case(_photos(keep=2), "only 2 sharp, readable photos (need 3)", "photos"),
    "photos_none": Case(_photos(keep=0), "no PNG/JPEG photos", "photos"),
    "poses_not_utf8": Case(_poses(lambda p: b'{"0000.png": "\xe9"}'), "cannot read poses", "poses.json"),
    "poses_truncated": Case(_poses(lambda p: json.dumps(p).encode()[:100]), "cannot read poses", "poses.json"),
    "poses_not_rigid": Case(_poses(_not_rigid), "not a rotation plus translation", "poses.json"),
    "poses_of_other_photos": Case(
        _poses(lambda p: json.dumps({f"x{k}": v for k, v in p.items()}).encode()),
        "no selected photo has a pose",
        "photos",
    ),
    "model_missing": Case(
        lambda s, o, t: reconstruct_argv(s, o, "--model", str(t / "nomodel")), "not a model folder", "nomodel"
    ),
    "model_weights_damaged": Case(_damaged_model, "cannot read the weights", "model.pt"),
    "resolution_too_small": Case(lambda s, o, t: reconstruct_argv(s, o)[:5] + ["4"], "need 8 to 16384", "--resolution"),
    "out_is_a_file": Case(_out(_a_file), "is a file, not a folder", "result.txt"),
    "out_is_users_folder": Case(_out(_user_folder), "not empty and not an ntp result folder", "mine"),
    "out_is_the_scan": Case(_out(lambda s, t: s), "is the input folder", "scan"),
    "out_inside_the_scan": Case(_out(lambda s, t: s / "result"), "is inside the input folder", "result"),
    "register_out_is_a_file": Case(_out(_a_file, "register"), "is a file, not a folder", "result.txt"),
    "virtual_scan_into_users_folder": Case(_out(_user_folder, "virtual-scan"), "not an ntp scan folder", "mine"),
    "demo_into_users_folder": Case(_out(_user_folder, "demo"), "not an ntp demo folder", "mine"),
    "cache_is_users_folder": Case(
        lambda s, o, t: reconstruct_argv(s, o, "--cache", str(_user_folder(s, t))), "not an ntp cache folder", "mine"
    ),
    "cache_is_the_result": Case(
        lambda s, o, t: reconstruct_argv(s, o, "--cache", str(o)), "is an ntp result folder, not a cache", "out"
    ),
    "cache_inside_the_scan": Case(
        lambda s, o, t: reconstruct_argv(s, o, "--cache", str(s / "cache")), "inside the input folder", "cache"
    ),
    "threads_negative": Case(lambda s, o, t: reconstruct_argv(s, o, "--threads", "-1"), "need 0 to", "--threads"),
    # what a hostile user found (#70): numbers without bounds, links, typos, devices as files
    "resolution_too_large": Case(
        lambda s, o, t: reconstruct_argv(s, o)[:5] + ["100000"] + reconstruct_argv(s, o)[6:],
        "need 8 to 16384",
        "--resolution",
    ),
    "resolution_overflows": Case(
        lambda s, o, t: reconstruct_argv(s, o)[:5] + ["99999999999999999999"] + reconstruct_argv(s, o)[6:],
        "need 8 to 16384",
        "--resolution",
    ),
    "threads_too_many": Case(
        lambda s, o, t: reconstruct_argv(s, o, "--threads", "99999999999"), "need 0 to", "--threads"
    ),
    "blur_margin_nan": Case(
        lambda s, o, t: reconstruct_argv(s, o, "--blur-margin", "nan"), "not a finite number", "--blur-margin"
    ),
    "board_missing": Case(_board(None), "key 'board': board.json does not exist", "scan.toml"),
    "board_truncated": Case(
        _board(json.dumps(board_for_paper("A4").to_json()).encode()[:60]), "cannot read the board layout", "board.json"
    ),
    "board_foreign": Case(
        _board(json.dumps({"0000.png": np.eye(4).tolist()}).encode()), "not an ntp board layout", "board.json"
    ),
    "board_unknown_dictionary": Case(
        _board(json.dumps({**board_for_paper("A4").to_json(), "dictionary": "DICT_9X9"}).encode()),
        "unknown marker dictionary",
        "board.json",
    ),
    "scan_toml_typo": Case(
        _toml(b'mesh = "mesh.obj"\nphotos = "photos"\ndevice = "device.toml"\npose = "poses.json"\n'),
        "key 'pose': unknown key (did you mean 'poses'?)",
        "scan.toml",
    ),
    "mesh_uv_nan": Case(
        _mesh(
            lambda m: Mesh(m.vertices, m.faces, np.where(np.arange(len(m.uv))[:, None] == 3, np.nan, m.uv), m.normals)
        ),
        "texture coordinate (vt) is not finite",
        "mesh.obj",
    ),
    "device_is_dev_zero": Case(
        lambda s, o, t: reconstruct_argv(s, o, "--device", "/dev/zero"),
        "is a character device, not a file",
        "/dev/zero",
    ),
    "device_fifo": Case(
        lambda s, o, t: (os.mkfifo(t / "device.toml"), reconstruct_argv(s, o, "--device", str(t / "device.toml")))[1],
        "is a FIFO (named pipe), not a file",
        "device.toml",
    ),
    "device_grid_count_huge": Case(
        _device_file(DEFAULT_DEVICE.read_bytes().replace(b"count = [32, 16]", b"count = [1e300, 1]")),
        "key 'emitters.count'",
        "broken.toml",
    ),
    "device_grid_count_too_many": Case(
        _device_file(DEFAULT_DEVICE.read_bytes().replace(b"count = [32, 16]", b"count = [200000, 200000]")),
        "is more than 65536",
        "broken.toml",
    ),
    "poses_is_a_fifo": Case(
        lambda s, o, t: (os.mkfifo(t / "p.json"), reconstruct_argv(s, o)[:-3] + ["--poses", str(t / "p.json")])[1],
        "is a FIFO (named pipe), not a file",
        "p.json",
    ),
    "cache_link_to_users_folder": Case(_cache_link(_users_atlas), "not an ntp cache folder", "mine"),
    "cache_link_into_the_scan": Case(_cache_link(lambda s, t: s), "is the input folder", "scan"),
    "virtual_scan_exposure_nan": Case(  # it wrote black photos, with numpy's warnings
        lambda s, o, t: ["virtual-scan", "--out", str(t / "vs"), "--exposure", "nan", "--views", "2", "--quiet"],
        "not a finite number",
        "--exposure",
    ),
    "progress_on_a_full_device": Case(
        lambda s, o, t: reconstruct_argv(s, o, "--progress", "/dev/full", "--resolution", "24"),
        "No space left on device",
        "/dev/full",
    ),
}


@pytest.mark.parametrize("name", list(CASES))
def test_refused_in_one_line_inputs_and_result_kept(name, copies, tmp_path, capsys):
    case, (scan, out) = CASES[name], copies
    argv = case.setup(scan, out, tmp_path)
    before = _state(tmp_path, out)
    capsys.readouterr()
    code = cli.main(argv)
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == case.code, lines
    assert all(ln.startswith("ntp: ") for ln in lines) and "Traceback" not in "".join(lines)
    assert case.message in lines[-1] and case.names in lines[-1], lines[-1]
    assert _state(tmp_path, out) == before  # inputs, the user's files and the previous result, byte for byte
    assert is_complete(out)
    assert not (scan / "result").exists()


def _state(tmp: Path, out: Path) -> dict:
    """Checksums of everything in ``tmp`` but ``out``'s cache (finished stages are kept by design)."""
    return {
        p.name: checksums(p, skip=("cache",) if p == out else ())
        if p.is_dir()
        else p.read_bytes()
        if p.is_file()
        else p.lstat().st_mode  # a FIFO or a link to a device: never read
        for p in tmp.iterdir()
    }


def test_a_folder_in_use_is_refused(copies, capsys):
    scan, out = copies
    before = checksums(out)
    with claim(out, "result"):
        assert cli.main(reconstruct_argv(scan, out)) == 2
    assert "another ntp run is writing to this folder" in capsys.readouterr().err
    assert checksums(out) == before


def test_a_read_only_out_is_refused(good, tmp_path, capsys):
    # as root (CI) permissions do not bind: the run drops to nobody's effective uid
    root = Path(tempfile_dir(tmp_path))
    scan, out = root / "scan", root / "out"
    shutil.copytree(good[0], scan, copy_function=shutil.copyfile)
    out.mkdir()
    os.chmod(out, 0o555)
    try:
        with _unprivileged():
            code = cli.main(reconstruct_argv(scan, out))
        lines = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(lines) == 1 and "cannot write here (Permission denied)" in lines[0]
        assert str(out) in lines[0] and list(out.iterdir()) == []
    finally:
        os.chmod(out, 0o755)
        shutil.rmtree(root)


def tempfile_dir(tmp_path: Path) -> str:
    """A folder anyone can enter (pytest's base folder is private to its user)."""
    import tempfile

    d = tempfile.mkdtemp(prefix="ntp-ro-")
    os.chmod(d, 0o755)
    return d


class _unprivileged:
    """Run as ``nobody`` (effective ids) when the tests run as root; otherwise nothing to do."""

    def __enter__(self):
        self.root = os.geteuid() == 0
        if self.root:
            os.setegid(65534)
            os.seteuid(65534)

    def __exit__(self, *exc):
        if self.root:
            os.seteuid(0)
            os.setegid(0)


# ------------------------------------------------------------------------------ damage repaired
def _run_ok(argv: list[str], capsys) -> tuple[list[str], dict]:
    capsys.readouterr()
    assert cli.main(argv) == 0
    lines = capsys.readouterr().err.strip().splitlines()
    return lines, json.loads(Path(argv[argv.index("--out") + 1], "report.json").read_text())


@pytest.mark.parametrize("damage", ["truncated_npy", "truncated_key", "edited_npz", "emptied_file_list"])
def test_a_damaged_cache_entry_is_recomputed(damage, good, copies, capsys):
    scan, out = copies
    target = {
        "truncated_npy": "traces/entries.npy",
        "truncated_key": "fit/key.json",
        "edited_npz": "fit/fit.npz",
        "emptied_file_list": "fit/key.json",
    }
    f = out / "cache" / target[damage]
    data = f.read_bytes()
    if damage == "emptied_file_list":  # a key that vouches for nothing must not vouch for a garbage fit.npz
        f.write_text(json.dumps({**json.loads(data), "files": {}}))
        (f.parent / "fit.npz").write_bytes(b"garbage")
    else:
        f.write_bytes(data[: len(data) // 2] if damage != "edited_npz" else data[:-5] + b"xxxxx")
    lines, rep = _run_ok(reconstruct_argv(scan, out), capsys)
    assert len(lines) == 1 and "cache entry damaged" in lines[0] and f.parent.name in lines[0]
    assert rep["recomputed_damaged_stages"] == [f.parent.name]
    assert outputs(out) == outputs(good[1])  # the same result, byte for byte


def test_leftovers_of_a_killed_run_are_removed(copies, capsys):
    scan, out = copies
    (out / "cache" / ".ntp-tmp.traces.k1ll3d00").mkdir()
    (out / ".ntp-tmp.result.k1ll3d00").mkdir()
    (out / ".ntp-tmp.normal.k1ll3d00.exr").write_bytes(b"half")
    _, rep = _run_ok(reconstruct_argv(scan, out), capsys)
    assert rep["cached_stages"] == ["select", "atlas", "traces", "fit"]
    assert not [p for p in out.rglob(".ntp-tmp.*")]


def test_a_cache_elsewhere_holds_the_stages_and_resumes(good, copies, tmp_path, capsys):
    scan, out = copies
    shutil.rmtree(out / "cache")
    elsewhere = tmp_path / "fast-disk" / "cache"
    _, rep = _run_ok(reconstruct_argv(scan, out, "--cache", str(elsewhere), "--threads", "1"), capsys)
    assert rep["cached_stages"] == [] and not (out / "cache").exists()
    assert json.loads((elsewhere / ".ntp").read_text()) == {"ntp": "cache"}
    assert {p.name for p in elsewhere.iterdir()} >= {"select", "atlas", "traces", "fit"}
    assert outputs(out) == outputs(good[1])
    _, rep = _run_ok(reconstruct_argv(scan, out, "--cache", str(elsewhere)), capsys)
    assert rep["cached_stages"] == ["select", "atlas", "traces", "fit"]


def test_changed_photos_with_a_poses_file_recompute(good, copies, capsys):
    scan, out = copies
    for p in sorted((scan / "photos").iterdir()):
        write_png(p, read_image(p) * 0.7)  # same names, same poses, other pixels
    _, rep = _run_ok(reconstruct_argv(scan, out), capsys)
    assert rep["cached_stages"] == ["atlas"]  # the photos' content is in the select stage's key, chained on
    assert outputs(out)["diffuse_albedo.exr"] != outputs(good[1])["diffuse_albedo.exr"]


def test_a_copied_scan_and_result_reuse_the_cache(good, copies, capsys):
    scan, out = copies  # copied with fresh file times, to other absolute paths
    time.sleep(0.01)
    _, rep = _run_ok(reconstruct_argv(scan, out), capsys)
    assert rep["cached_stages"] == ["select", "atlas", "traces", "fit"]
    assert outputs(out) == outputs(good[1])


def test_a_truncated_photo_is_named_and_left_out(copies, capsys):
    scan, out = copies
    png = sorted((scan / "photos").iterdir())[3]
    bad = png.with_suffix(".jpg")  # a JPEG cut in half decodes, its missing rows grey: must be refused
    _write_jpeg(bad, read_image(png))
    png.unlink()
    bad.write_bytes(bad.read_bytes()[: bad.stat().st_size // 2])
    lines, rep = _run_ok(reconstruct_argv(scan, out), capsys)
    assert len(lines) == 1 and bad.name in lines[0] and "truncated or corrupt" in lines[0]
    assert rep["photos"]["unreadable"] == [bad.name] and rep["photos"]["kept"] == 23


def _oiio_write(path: Path, pixels: np.ndarray, fmt: str) -> None:
    """Write ``pixels`` (H, W, C) to ``path`` as OpenImageIO's ``fmt`` in the format the bytes say
    (``.exr`` bytes under a ``.png`` name are written to a temporary ``.exr`` first)."""
    import OpenImageIO as oiio

    real = path.with_suffix(".exr") if fmt == "float" else path
    out = oiio.ImageOutput.create(str(real))
    out.open(str(real), oiio.ImageSpec(pixels.shape[1], pixels.shape[0], pixels.shape[2], oiio.TypeDesc(fmt)))
    out.write_image(np.ascontiguousarray(pixels))
    out.close()
    if real != path:
        os.replace(real, path)


def _rgba(p: Path) -> str:  # alpha 128: OpenImageIO premultiplied it on read, photos came in at half brightness
    img = np.round(read_image(p) * 255).astype(np.uint8)
    _oiio_write(p, np.concatenate([img, np.full((*img.shape[:2], 1), 128, np.uint8)], -1), "uint8")
    return p.name


def _float(p: Path) -> str:  # values > 1 became codes up to 1020 and wrapped modulo 256
    _oiio_write(p, read_image(p) * 4.0, "float")
    return p.name


def _grey(p: Path) -> str:  # was called a size mismatch
    _oiio_write(p, np.round(read_image(p)[..., :1] * 255).astype(np.uint8), "uint8")
    return p.name


def _huge(p: Path) -> str:  # a 1 MB PNG declaring 20000x20000 was decoded before its size was checked
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    rows = zlib.compress(bytes(20000 * (1 + 20000 * 3)), 9)
    header = struct.pack(">IIBBBBB", 20000, 20000, 8, 2, 0, 0, 0)
    p.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", rows) + chunk(b"IEND", b""))
    return p.name


def _fifo(p: Path) -> str:  # open() blocked, and the first Ctrl-C was ignored
    os.mkfifo(p.with_name("fifo.png"))
    return "fifo.png"


def _dev_zero(p: Path) -> str:  # hashed forever
    p.with_name("zero.png").symlink_to("/dev/zero")
    return "zero.png"


UNTRUSTED_PHOTOS = {
    "rgba_half_transparent": (_rgba, "pixels are not opaque (alpha < 1)"),
    "float_pixels_under_png": (_float, "holds float pixels"),
    "grayscale": (_grey, "a grayscale photo; the camera takes RGB"),
    "declares_20000x20000": (_huge, "20000x20000 image, expected 612x512"),
    "fifo": (_fifo, "is a FIFO (named pipe), not a file"),
    "link_to_dev_zero": (_dev_zero, "is a character device, not a file"),
}


def test_photos_ntp_cannot_trust_are_each_named_and_left_out(copies, capsys):
    """One scan with every kind at once (one run: the suite's time), each on its own photo."""
    scan, out = copies
    photos = sorted((scan / "photos").iterdir())
    expected = {make(photos[2 * k]): message for k, (make, message) in enumerate(UNTRUSTED_PHOTOS.values())}
    _oiio_write(scan / "photos" / "extra.exr", np.zeros((4, 4, 3), np.float32), "float")  # not a photo format
    (scan / "photos" / ".DS_Store").write_bytes(b"\0")  # hidden files are no one's photos
    lines, rep = _run_ok(reconstruct_argv(scan, out), capsys)
    assert lines[0] == f"ntp: warning: {scan / 'photos' / 'extra.exr'}: not a PNG/JPEG photo — skipped"
    assert len(lines) == 1 + len(expected), lines
    for name, message in expected.items():
        assert [ln for ln in lines if f"photos/{name}:" in ln and message in ln], (name, lines)
    assert sorted(rep["photos"]["unreadable"]) == sorted(expected)
    replaced = [n for n in expected if n in {p.name for p in photos}]  # the others were added beside them
    assert rep["photos"]["kept"] == 24 - len(replaced) and len(replaced) == 4


def test_photos_in_16_bits_are_read_as_their_8_bit_codes(good, copies, capsys):
    scan, out = copies
    for p in sorted((scan / "photos").iterdir()):  # a converter's 16-bit copy: code * 257
        _oiio_write(p, np.round(read_image(p) * 255).astype(np.uint16) * 257, "uint16")
    lines, rep = _run_ok(reconstruct_argv(scan, out), capsys)
    assert lines == [] and rep["photos"]["kept"] == 24
    assert outputs(out) == outputs(good[1])  # the same codes: the same result, byte for byte


def _write_jpeg(path: Path, img: np.ndarray) -> None:
    import OpenImageIO as oiio

    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(img.shape[1], img.shape[0], 3, oiio.UINT8))
    out.write_image(np.round(img[..., :3] * 255).astype(np.uint8))
    out.close()


# ------------------------------------------------------------------------------ signals and full disks
def _ntp(*args: str, preexec=None, **kw) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "ntp_engine.cli", *args]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=preexec, **kw)


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _wait_for_stage(progress: Path, stage: str, proc: subprocess.Popen, timeout: float = 120) -> None:
    t0 = time.time()
    while time.time() - t0 < timeout and proc.poll() is None:
        if progress.is_file() and f'"stage": "{stage}"' in progress.read_text():
            return
        time.sleep(0.05)
    if proc.poll() is None:
        raise AssertionError(f"stage {stage} never started")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGKILL])
def test_interrupted_runs_resume_to_the_same_result(sig, good, copies, tmp_path):
    scan, out = copies
    progress = tmp_path / "progress.jsonl"
    for _ in range(5):  # a busy machine may let the small run finish before the signal lands: again
        for stage in ("traces", "fit"):  # the run has the traces (seconds) and the fit to do
            shutil.rmtree(out / "cache" / stage, ignore_errors=True)
        progress.unlink(missing_ok=True)
        # a shell's background job (CI may be one) ignores SIGINT, and a child inherits that: a user's
        # terminal does not
        proc = _ntp(*reconstruct_argv(scan, out), "--progress", str(progress), preexec=_default_sigint)
        _wait_for_stage(progress, "traces", proc)
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=120)
        if proc.returncode != 0:
            break
    if sig in (signal.SIGINT, signal.SIGTERM):  # kill, a scheduler's time limit: as Ctrl-C
        word = "interrupted" if sig == signal.SIGINT else "terminated"
        assert proc.returncode == 128 + sig
        assert err.strip() == f"ntp: {word} — finished stages are kept, re-run to resume"
        assert not [p for p in out.rglob(".ntp-tmp.*")]  # an interrupt cleans up after itself
    else:
        assert proc.returncode == -signal.SIGKILL
    assert is_complete(out)  # the previous result is untouched
    rerun = _ntp(*reconstruct_argv(scan, out))
    _, err = rerun.communicate(timeout=300)
    assert rerun.returncode == 0, err
    rep = json.loads((out / "report.json").read_text())
    assert rep["cached_stages"] == ["select", "atlas"]
    assert outputs(out) == outputs(good[1]) and not [p for p in out.rglob(".ntp-tmp.*")]


def test_a_full_disk_is_one_line_and_the_result_survives(copies):
    scan, out = copies
    before = outputs(out)

    def small_files():  # writes past 64 KiB fail as on a full disk (EFBIG here; ENOSPC reads the same)
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (64 * 1024, 64 * 1024))

    argv = reconstruct_argv(scan, out)
    argv[argv.index("--resolution") + 1] = "32"  # a new atlas: the traces are written again
    proc = _ntp(*argv, preexec=small_files)
    _, err = proc.communicate(timeout=300)
    lines = err.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, err
    assert "File too large" in lines[0] and str(out / "cache") in lines[0]
    assert outputs(out) == before and is_complete(out) and not [p for p in out.rglob(".ntp-tmp.*")]


@pytest.fixture
def small_disk(tmp_path):
    """A 3 MB file system (tmpfs): where the suite may mount one (root with CAP_SYS_ADMIN)."""
    disk = tmp_path / "disk"
    disk.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=3m", "tmpfs", str(disk)], capture_output=True).returncode:
        pytest.skip("cannot mount a small file system here (needs root with CAP_SYS_ADMIN)")
    yield disk
    subprocess.run(["umount", str(disk)], check=True)


def test_a_disk_filling_up_under_the_memory_mapped_trace_table_is_one_line(scan24, small_disk):
    """The trace table is memory-mapped; a page first written on a full disk was a SIGBUS (exit 135,
    no word, temporaries left). Its blocks are reserved when it is made: ENOSPC, one line."""
    out = small_disk / "out"
    proc = _ntp(*reconstruct_argv(scan24, out, "--resolution", "64"))  # a table over the 3 MB
    _, err = proc.communicate(timeout=300)
    lines = err.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, err
    assert "No space left on device" in lines[0] and str(out / "cache" / "traces") in lines[0]
    assert not [p for p in out.rglob(".ntp-tmp.*")] and not is_complete(out)


def test_a_scan_far_from_the_world_origin_gives_the_same_maps(good, copies, capsys):
    """A mesh and poses moved together by (1000, 1000, 0) m: float32 positions had steps of 0.06 mm
    there (coverage 88%, normals off by up to 0.67 rad, exit 0). Work is in the scan's local frame."""
    scan, out = copies
    shift = np.array([1000.0, 1000.0, 0.0])
    mesh = load_mesh(scan / "mesh.obj")
    save_obj(scan / "mesh.obj", Mesh(mesh.vertices + shift, mesh.faces, mesh.uv, mesh.normals), digits=12)
    back = np.eye(4)
    back[:3, 3] = -shift
    poses = json.loads((scan / "ground_truth" / "poses.json").read_text())
    far = {n: (np.array(m) @ back).tolist() for n, m in poses.items()}
    (scan / "ground_truth" / "poses.json").write_text(json.dumps(far))
    lines, rep = _run_ok(reconstruct_argv(scan, out), capsys)
    assert lines == [] and rep["texels"]["coverage"] == 1.0
    for name in ("normal", "diffuse_albedo", "specular_albedo", "roughness"):
        near, got = read_image(good[1] / f"{name}.exr"), read_image(out / f"{name}.exr")
        np.testing.assert_allclose(got, near, atol=2e-3, err_msg=name)
    near, got = load_mesh(good[1] / "mesh.obj"), load_mesh(out / "mesh.obj")  # the result is in the world's frame
    np.testing.assert_allclose(got.vertices, near.vertices + shift, atol=1e-6)
