"""The Blender extension: the manifest against Blender's own schema rules (its bundled packager's
validator, strict, and the add-on tag list), and the build step (engine wheel only, to stay offline
and fast) producing a zip that Blender's validator accepts."""

import importlib.util
import os
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import bpy  # noqa: F401  (locates the bundled packager)

ROOT = Path(__file__).resolve().parents[2]

import build_extension  # noqa: E402


def _validator():
    spec = importlib.util.spec_from_file_location("blender_ext", build_extension.blender_ext())
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _errors(path: Path) -> list[str]:
    r = _validator().pkg_manifest_from_toml_and_validate_all_errors(str(path), strict=True)
    return r if isinstance(r, list) else []


def test_manifest_follows_the_schema(tmp_path):
    from _bpy_internal.extensions.tags import addons as valid_tags

    manifest = tomllib.loads((ROOT / "blender_manifest.toml").read_text())
    assert _errors(ROOT / "blender_manifest.toml") == []
    assert manifest["schema_version"] == "1.0.0" and manifest["blender_version_min"] == "4.2.0"
    assert manifest["blender_version_max"] == "5.1.0"  # cp311 wheels: Blender 4.2-5.0 run Python 3.11
    assert set(manifest["tags"]) <= valid_tags and manifest["platforms"] == ["linux-x64"]
    assert all(reason and len(reason) <= 64 for reason in manifest["permissions"].values())
    # the validator is not a rubber stamp: the faults it must catch
    text = (ROOT / "blender_manifest.toml").read_text()
    for bad in (
        text.replace('id = "ntp"', 'id = "ntp-addon"'),
        text.replace('version = "0.1.0"', 'version = "one"'),
        text.replace('files = "', 'files = "' + "x" * 70),
        text.replace('schema_version = "1.0.0"\n', ""),
    ):
        (tmp_path / "blender_manifest.toml").write_text(bad)
        assert _errors(tmp_path / "blender_manifest.toml"), bad[:80]


def test_build_makes_a_valid_installable_zip(tmp_path):
    r = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "build_extension.py"), "--out", str(tmp_path), "--no-dependency-wheels"],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    zips = list(tmp_path.glob("ntp-*.zip"))
    assert len(zips) == 1
    v = subprocess.run(
        [sys.executable, str(build_extension.blender_ext()), "validate", str(zips[0])], capture_output=True, text=True
    )
    assert v.returncode == 0, v.stdout + v.stderr
    with zipfile.ZipFile(zips[0]) as z:
        names = set(z.namelist())
        assert {"__init__.py", "blender_manifest.toml", "material.py", "operators.py"} <= names
        manifest = tomllib.loads(z.read("blender_manifest.toml").decode())
        wheel = next(n for n in names if n.startswith("wheels/ntp_engine-"))
        assert manifest["wheels"] == [f"./{wheel}"]
        with zipfile.ZipFile(z.open(wheel)) as w:
            inner = set(w.namelist())
    assert "ntp_engine/assets/devices/ntp_led_32x16.toml" in inner and "ntp_engine/cli.py" in inner
    assert any(n.startswith("ntp_engine/assets/models/compact/") for n in inner)
    assert not [n for n in inner if "/models/compare_" in n or "/assets/demo/" in n]  # bench-only: not shipped
    assert "ntp_engine/docs/blender.md" in inner  # the help panel's guides
    assert zips[0].stat().st_size < 20e6
    # installed into Blender's extension repository as a user does, it registers from there
    probe = (
        "import sys, bpy; "
        "r = bpy.ops.extensions.package_install_files(filepath=sys.argv[-1], repo='user_default', "
        "enable_on_install=True); "
        "import ntp_engine.io.assets as a; m = sys.modules['bl_ext.user_default.ntp']; "
        "p = bpy.context.preferences.addons['bl_ext.user_default.ntp'].preferences; "
        "print(r, m.__file__, a.DOCS_DIR, p.model, hasattr(bpy.ops.ntp, 'reconstruct'), "
        "hasattr(bpy.ops.import_scene, 'ntp_result'))"
    )
    home = tmp_path / "blender-home"
    env = {**os.environ, "BLENDER_USER_RESOURCES": str(home)}
    r = subprocess.run(
        [sys.executable, "-c", probe, str(zips[0])], capture_output=True, text=True, env=env, cwd=tmp_path
    )
    assert r.returncode == 0, r.stderr[-2000:]
    status, module, docs, model, has_op, has_import = r.stdout.split()[-6:]
    assert status == "{'FINISHED'}" and module.startswith(str(home / "extensions" / "user_default" / "ntp"))
    assert docs.startswith(str(home)) and model == "compact" and has_op == has_import == "True"


def test_engine_wheel_installs_and_finds_its_assets(tmp_path):
    wheel = build_extension.engine_wheel(tmp_path)
    target = tmp_path / "site"
    r = subprocess.run(
        [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(target), str(wheel)],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    probe = (
        "import ntp_engine.io.assets as a, ntp_engine.scanner.device_file as d, ntp_engine.learn.models as m; "
        "print(a.ASSETS); print(d.load_scanner().name); print(m.resolve(None))"
    )
    out = subprocess.run(
        [sys.executable, "-c", probe],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env={"PYTHONPATH": str(target), "PATH": "/usr/bin:/bin"},
    )
    assert out.returncode == 0, out.stderr
    assets, name, model = out.stdout.split()
    assert assets.startswith(str(target)) and name == "ntp-led-32x16" and model.startswith(str(target))
