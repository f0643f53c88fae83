"""Where the shipped assets live: ``assets/`` of the source checkout, else the copy a wheel or the
Blender extension puts inside the package. One home for every asset path."""

from __future__ import annotations

from pathlib import Path

_PACKAGE = Path(__file__).resolve().parent.parent
ASSETS = next((p for p in (_PACKAGE.parent / "assets", _PACKAGE / "assets") if p.is_dir()), _PACKAGE.parent / "assets")
DEVICES_DIR = ASSETS / "devices"  # scanner calibrations (TOML)
MODELS_DIR = ASSETS / "models"  # shipped trace networks
DEMO_DIR = ASSETS / "demo"  # the demo asset: mesh.obj + ground_truth/
# the user guides: docs/ of the checkout, else the copy the extension's wheel carries
DOCS_DIR = next((p for p in (_PACKAGE.parent / "docs", _PACKAGE / "docs") if p.is_dir()), _PACKAGE.parent / "docs")
