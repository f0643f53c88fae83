"""Property-based fuzz of the readers of a user's files — scan.toml, the device file, a poses file,
a mesh: whatever the bytes, the answer is a result or one ``NtpInputError`` line naming the file,
never another exception (a traceback for the user)."""

from __future__ import annotations

import json
import shutil
import tomllib
from pathlib import Path

import numpy as np
import pytest
import tomli_w
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ntp_engine.io.errors import NtpInputError
from ntp_engine.io.mesh import load_mesh
from ntp_engine.scanner.device_file import DEFAULT_DEVICE, load_scanner
from ntp_engine.scanner.scan_folder import SCAN_KEYS, load_poses, load_scan

FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])

# values of every TOML/JSON type, the numbers at the edges (huge, negative, NaN, infinite)
NUMBERS = st.one_of(
    st.integers(min_value=-(2**63), max_value=2**63 - 1),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0, 1, -1, 2**31, 1e300, -1e-300]),
)
SCALARS = st.one_of(NUMBERS, st.booleans(), st.text(max_size=12))
VALUES = st.recursive(
    SCALARS,
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=12,
)


def _one_line_naming(err: NtpInputError, path: Path) -> None:
    assert "\n" not in str(err) and str(path.name) in str(err), str(err)


def _mutated(table: dict, draw_key: str, value) -> dict:
    """``table`` with the dotted ``draw_key`` set to ``value`` (tables made on the way)."""
    node = table
    *parents, last = draw_key.split(".")
    for p in parents:
        node = node.setdefault(p, {}) if isinstance(node.get(p, {}), dict) else {}
    node[last] = value
    return table


DEVICE_TABLE = tomllib.loads(DEFAULT_DEVICE.read_text())
DEVICE_KEYS = [
    f"{section}.{key}" if isinstance(DEVICE_TABLE[section], dict) else section
    for section in DEVICE_TABLE
    for key in (DEVICE_TABLE[section] if isinstance(DEVICE_TABLE[section], dict) else [None])
]


@FUZZ
@given(key=st.sampled_from([*DEVICE_KEYS, "emitters.extra", "camera.widht", "nonsense"]), value=VALUES)
def test_the_device_reader_answers_a_scanner_or_one_line(tmp_path, key, value):
    path = tmp_path / "device.toml"
    table = _mutated(json.loads(json.dumps(DEVICE_TABLE)), key, value)
    table["pattern"] = str(DEFAULT_DEVICE.parent / DEVICE_TABLE["pattern"]) if key != "pattern" else table["pattern"]
    try:
        path.write_text(tomli_w.dumps(table))
    except (TypeError, ValueError):
        return  # not representable in TOML: no file a user could have
    try:
        load_scanner(path)
    except NtpInputError as err:
        _one_line_naming(err, path)


@FUZZ
@given(data=st.binary(max_size=300))
def test_the_device_reader_answers_bytes_in_one_line(tmp_path, data):
    path = tmp_path / "device.toml"
    text = DEFAULT_DEVICE.read_bytes()
    cut = len(data) % len(text)
    path.write_bytes(text[:cut] + data + text[cut:])  # garbage spliced into a real file
    try:
        load_scanner(path)
    except NtpInputError as err:
        _one_line_naming(err, path)


@pytest.fixture(scope="module")
def scan_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("fuzz") / "scan"
    (folder / "photos").mkdir(parents=True)
    (folder / "photos" / "0000.png").write_bytes(b"")
    (folder / "mesh.obj").write_text("v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nf 1 2 3\n")
    shutil.copy(DEFAULT_DEVICE, folder / "device.toml")
    text = DEFAULT_DEVICE.read_text()
    (folder / "device.toml").write_text(text.replace('pattern = "', f'pattern = "{DEFAULT_DEVICE.parent}/'))
    (folder / "poses.json").write_text(json.dumps({"0000.png": np.eye(4).tolist()}))
    return folder


@FUZZ
@given(table=st.dictionaries(st.sampled_from([*SCAN_KEYS, "pose", "mesh_", "x"]), VALUES, max_size=6))
def test_the_scan_reader_answers_a_scan_or_one_line(scan_folder, table):
    for key, real in (("mesh", "mesh.obj"), ("photos", "photos"), ("device", "device.toml")):
        table.setdefault(key, real)
    try:
        (scan_folder / "scan.toml").write_text(tomli_w.dumps(table))
    except (TypeError, ValueError):
        return
    try:
        load_scan(scan_folder)
    except NtpInputError as err:
        assert "\n" not in str(err), str(err)


POSE = st.lists(st.lists(NUMBERS, min_size=0, max_size=5), min_size=0, max_size=5)


@FUZZ
@given(poses=st.one_of(st.dictionaries(st.text(max_size=10), st.one_of(POSE, VALUES), max_size=4), VALUES))
def test_the_poses_reader_answers_poses_or_one_line(tmp_path, poses):
    path = tmp_path / "poses.json"
    path.write_text(json.dumps(poses))
    try:
        got = load_poses(path)
    except NtpInputError as err:
        _one_line_naming(err, path)
        return
    assert all(m.shape == (4, 4) and np.isfinite(m).all() for m in got.values())


@FUZZ
@given(data=st.binary(max_size=400))
def test_the_poses_reader_answers_bytes_in_one_line(tmp_path, data):
    path = tmp_path / "poses.json"
    path.write_bytes(data)
    try:
        load_poses(path)
    except NtpInputError as err:
        _one_line_naming(err, path)


FLOAT_TEXT = st.one_of(NUMBERS.map(str), st.sampled_from(["nan", "inf", "-inf", "1e400", "x", ""]))
OBJ_LINE = st.one_of(
    st.tuples(st.just("v"), FLOAT_TEXT, FLOAT_TEXT, FLOAT_TEXT),
    st.tuples(st.just("vt"), FLOAT_TEXT, FLOAT_TEXT),
    st.tuples(st.just("vn"), FLOAT_TEXT, FLOAT_TEXT, FLOAT_TEXT),
    st.tuples(st.just("f"), *[st.integers(-5, 12).map(str) | st.sampled_from(["1/1", "2/2/2", "3//3", "0", "x"])] * 3),
    st.text(max_size=20).map(lambda t: (t,)),
)


@FUZZ
@given(lines=st.lists(OBJ_LINE, max_size=14))
def test_the_mesh_reader_answers_a_mesh_or_one_line(tmp_path, lines):
    path = tmp_path / "mesh.obj"
    base = ["v 0 0 0", "v 0.1 0 0", "v 0 0.1 0", "vt 0 0", "vt 1 0", "vt 0 1", "f 1/1 2/2 3/3"]
    path.write_text("\n".join(base + [" ".join(parts) for parts in lines]) + "\n")
    try:
        mesh = load_mesh(path)
    except NtpInputError as err:
        _one_line_naming(err, path)
        return
    assert np.isfinite(mesh.vertices).all() and len(mesh.faces) > 0
    assert mesh.faces.min() >= 0 and mesh.faces.max() < len(mesh.vertices)
    assert mesh.uv is None or np.isfinite(mesh.uv).all()
