"""Build the installable Blender extension zip (linux-x64) with Blender's own packager.

    python tools/build_extension.py [--out dist] [--no-dependency-wheels] [--torch-index URL]

Stages ``build/extension/ntp/``: the add-on modules at the root (Blender imports the extension as
a package), ``blender_manifest.toml`` with a ``wheels`` list, and ``wheels/``: ``ntp_engine`` as a
wheel carrying the shipped devices, the default model and the user guides (``docs/*.md``) inside
the package — not the bench-only comparison networks nor the demo asset — plus the engine's
dependencies for CPython 3.11 on manylinux x86-64: torch's CPU build from PyTorch's CPU index
(``TORCH_CPU_INDEX``; PyPI's Linux torch is the CUDA build, gigabytes of nvidia wheels), scipy,
pycolmap, xatlas, OpenImageIO, embreex, trimesh, scikit-image, pillow, tomli_w, tqdm, numba, threadpoolctl and what they
need. numpy is left out: Blender ships it. Then ``blender_ext.py validate`` and ``build`` (from
the bpy module's bundled ``bl_pkg``) check and zip it.

Other platforms: run with ``--platform`` set to pip's tag for the target (``win_amd64``,
``macosx_11_0_arm64``, ...) and the manifest's ``platforms`` to match (``windows-x64``,
``macos-arm64``); torch's CPU wheels for Windows/macOS are on PyPI as the default build.
"""

from __future__ import annotations

import argparse
import base64
import hashlib
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import tomli_w

ROOT = Path(__file__).resolve().parent.parent
EXCLUDE = {
    "numpy",
    "bpy",
    "matplotlib",
    "pytest",
    "hypothesis",
    "ruff",
    "mypy",
    "ray",
}  # Blender ships numpy; ray is the command line's (--ray, ntp batch); the rest is dev-only
PLATFORMS = ["manylinux_2_28_x86_64", "manylinux2014_x86_64"]  # torch's CPU wheel is 2_28
TORCH_CPU_INDEX = "https://download.pytorch.org/whl/cpu"  # torch==X resolves to X+cpu there
GPU_ONLY = ("nvidia", "triton")  # CUDA runtime wheels: never shipped (the extension runs on the CPU)
# assets only the benchmarks and the demo use (the comparison networks, the demo object): not shipped
BENCH_ONLY = ("models/compare_", "demo/")


def blender_ext() -> Path:
    """The path of the extension packager bundled with bpy (bl_pkg's blender_ext.py)."""
    import bpy  # noqa: F401  (locates the bundled packager)

    scripts = Path(bpy.__file__).resolve().parents[2]  # .../bpy/<version>/scripts/modules/bpy/__init__.py
    found = sorted(scripts.glob("addons_core/bl_pkg/cli/blender_ext.py"))
    if not found:
        raise SystemExit("bpy's bl_pkg/cli/blender_ext.py not found")
    return found[-1]


def dependency_pins() -> list[str]:
    """The engine's pinned runtime dependencies (requirements.txt, less bpy and test-only tools)."""
    pins = []
    for line in (ROOT / "requirements.txt").read_text().splitlines():
        line = line.split("#")[0].strip()
        if line and line.split("==")[0].split(">")[0].lower() not in EXCLUDE:
            pins.append(line)
    return pins


def engine_wheel(wheels: Path) -> Path:
    """``ntp_engine`` with ``assets/`` inside the package as a pure-Python wheel, written directly
    (a wheel is a zip with a ``.dist-info``; no build backend needed, so this works offline)."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    name, version = "ntp_engine", project["version"]
    files: list[tuple[str, Path]] = []
    for base, prefix in ((ROOT / "ntp_engine", "ntp_engine"), (ROOT / "assets", "ntp_engine/assets")):
        for f in sorted(base.rglob("*")):
            rel = f.relative_to(base).as_posix()
            shipped = not (prefix.endswith("assets") and rel.startswith(BENCH_ONLY))
            if f.is_file() and shipped and "__pycache__" not in f.parts and f.suffix != ".pyc":
                files.append((f"{prefix}/{rel}", f))
    files += [(f"ntp_engine/docs/{f.name}", f) for f in sorted((ROOT / "docs").glob("*.md"))]
    dist = f"{name}-{version}.dist-info"
    meta = {
        f"{dist}/METADATA": f"Metadata-Version: 2.1\nName: ntp-engine\nVersion: {version}\n"
        f"Summary: {project['description']}\nRequires-Python: {project['requires-python']}\n",
        f"{dist}/WHEEL": "Wheel-Version: 1.0\nGenerator: ntp tools/build_extension.py\nRoot-Is-Purelib: true\n"
        "Tag: py3-none-any\n",
    }
    target = wheels / f"{name}-{version}-py3-none-any.whl"
    record = []

    def entry(data: bytes, arc: str) -> None:
        digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
        record.append(f"{arc},sha256={digest},{len(data)}")
        z.writestr(arc, data)

    with zipfile.ZipFile(target, "w", zipfile.ZIP_DEFLATED) as z:
        for arc, f in files:
            entry(f.read_bytes(), arc)
        for arc, text in meta.items():
            entry(text.encode(), arc)
        z.writestr(f"{dist}/RECORD", "\n".join(record + [f"{dist}/RECORD,,"]) + "\n")
    return target


def build(
    out: Path,
    with_dependencies: bool = True,
    platforms: list[str] | None = None,
    torch_index: str = TORCH_CPU_INDEX,
) -> Path:
    """Build the installable extension zip (the add-on, manifest and wheels) into ``out``."""
    stage = ROOT / "build" / "extension" / "ntp"
    if stage.exists():
        shutil.rmtree(stage)
    wheels = stage / "wheels"
    wheels.mkdir(parents=True)
    for f in [*(ROOT / "ntp_addon").glob("*.py"), *(ROOT / "ntp_addon").glob("*.osl")]:
        shutil.copy(f, stage / f.name)
    engine_wheel(wheels)
    if with_dependencies:
        tags = [a for p in (platforms or PLATFORMS) for a in ("--platform", p)]
        subprocess.run(
            [
                sys.executable,
                "-m",
                "pip",
                "download",
                "-q",
                "-d",
                str(wheels),
                "--only-binary=:all:",
                *tags,
                "--python-version",
                "3.11",
                "--implementation",
                "cp",
                "--extra-index-url",
                torch_index,
                *dependency_pins(),
            ],
            check=True,
        )
        for w in wheels.glob("*.whl"):
            if w.name.split("-")[0].lower() in EXCLUDE or w.name.lower().startswith(GPU_ONLY):
                w.unlink()
        torch = [w.name for w in wheels.glob("torch-*.whl")]
        if not torch or ("+cpu" not in torch[0] and "linux" in torch[0]):
            raise SystemExit(f"torch's CPU build not found at {torch_index} (got {torch}); pass --torch-index")
    manifest = tomllib.loads((ROOT / "blender_manifest.toml").read_text())
    manifest["wheels"] = [f"./wheels/{w.name}" for w in sorted(wheels.glob("*.whl"))]
    (stage / "blender_manifest.toml").write_text(tomli_w.dumps(manifest))
    tool = blender_ext()
    subprocess.run([sys.executable, str(tool), "validate", str(stage)], check=True)
    out.mkdir(parents=True, exist_ok=True)
    subprocess.run(
        [sys.executable, str(tool), "build", "--source-dir", str(stage), "--output-dir", str(out)], check=True
    )
    return next(out.glob(f"{manifest['id']}-{manifest['version']}*.zip"))


def main() -> int:
    """Command line: build the extension zip into --out."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=ROOT / "dist")
    p.add_argument(
        "--no-dependency-wheels",
        action="store_true",
        help="only the ntp_engine wheel (for tests; the add-on then needs the deps installed)",
    )
    p.add_argument("--platform", action="append", default=None, help="pip platform tag(s) of the target")
    p.add_argument("--torch-index", default=TORCH_CPU_INDEX, help="index with torch's CPU build (or a mirror)")
    a = p.parse_args()
    print(f"wrote {build(a.out, not a.no_dependency_wheels, a.platform, a.torch_index)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
