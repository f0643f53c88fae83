"""``RESULT/index.html``: one self-contained page of a result (no network, no other file) — the
asset's ``.glb`` in a three.js view with a movable light and a turntable, the maps side by side,
the coverage and uncertainty layers, the registration picture and the report's numbers.

The 3D view's script is ``web/viewer.js`` with three.js bundled in (``make setup`` builds
``web/dist/viewer.js`` with esbuild where npm exists; pinned in the Makefile). Without the bundle or
without a ``.glb`` the page says which and how to get it; everything else is still there.
Images are embedded as PNG data (maps in their UV layout, as ``previews/`` holds them).
"""

from __future__ import annotations

import base64
import html
import io
import json
import math
from pathlib import Path

import numpy as np
from PIL import Image

from ..io.atomic import write_text_atomic
from ..io.blender_process import GLB_HOWTO
from ..io.errors import NtpInputError
from ..io.images import read_image
from ..io.mesh import load_mesh
from ..io.output_folder import PAGE as PAGE_FILE
from ..io.output_folder import REPORT as REPORT_FILE
from ..io.texels import rasterize
from .coverage_layers import LAYERS, ramp_colours

VIEWER_BUNDLE = Path(__file__).resolve().parent / "web" / "dist" / "viewer.js"
MAP_PREVIEWS = (  # previews/ file, caption (result.write_result's display scales)
    ("diffuse_albedo.png", "diffuse albedo ρd (sRGB)"),
    ("specular_albedo.png", "specular albedo ρs / 10 (gamma 2.2)"),
    ("normal.png", "normal, object space (xyz → rgb)"),
    ("tangent.png", "tangent, object space (xyz → rgb)"),
    ("roughness.png", "roughness αx (R), αy (G), / 0.5"),
)
UNSEEN_GREY = 0.25  # layer texels outside the UV atlas: no surface there


def png_data(pixels: np.ndarray) -> str:
    """A ``data:`` URL of ``pixels (H, W, 3|4)`` in [0, 1] as an 8-bit PNG."""
    q = np.round(np.clip(np.nan_to_num(pixels), 0.0, 1.0) * 255).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(q).save(buf, format="PNG", optimize=False)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def file_data(path: Path, mime: str) -> str:
    """A ``data:`` URL of a file's bytes."""
    return f"data:{mime};base64," + base64.b64encode(path.read_bytes()).decode("ascii")


def layer_images(result: Path) -> list[tuple[str, str, tuple[str, str], str]]:
    """(label, PNG data URL, legend, hint) for each coverage layer the result has, in its UV layout;
    texels off the mesh's UV atlas grey."""
    out = []
    atlas = None
    cache: dict[str, np.ndarray] = {}
    for layer in LAYERS.values():
        path = result / layer.file
        if not path.is_file():
            continue
        if layer.file not in cache:
            cache[layer.file] = read_image(path)
        values = cache[layer.file]
        if atlas is None:
            tex = rasterize(load_mesh(result / "mesh.obj"), (values.shape[0], values.shape[1]))
            atlas = np.zeros(values.shape[:2], bool)
            atlas[tex.row, tex.col] = True
        rgb = ramp_colours(values[..., layer.channel], layer)
        rgb[~atlas] = UNSEEN_GREY
        out.append((layer.label, png_data(rgb), layer.legend, layer.hint))
    return out


def _numbers(report: dict, prefix: str = "") -> list[tuple[str, str]]:
    """The report's scalars as (dotted key, text) rows, nested dictionaries flattened."""
    rows = []
    for key, value in report.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            rows += _numbers(value, name + ".")
        elif isinstance(value, float):
            rows.append((name, "nan" if math.isnan(value) else f"{value:.4g}"))
        elif isinstance(value, (int, str, bool)) or value is None:
            rows.append((name, str(value)))
        elif isinstance(value, list) and len(value) <= 8 and all(isinstance(v, (int, float, str)) for v in value):
            rows.append((name, ", ".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in value)))
    return rows


def _figure(src: str, caption: str) -> str:
    text = html.escape(caption)
    return f'<figure><img src="{src}" alt="{text}"><figcaption>{text}</figcaption></figure>'


STYLE = """
body { font: 14px/1.4 system-ui, sans-serif; margin: 0 auto; max-width: 1200px; padding: 1em; }
body { background: #fafafa; color: #222; }
h1 { font-size: 1.4em; } h2 { font-size: 1.15em; margin-top: 1.6em; }
#ntp-view { display: flex; gap: 1em; flex-wrap: wrap; align-items: flex-start; }
#ntp-canvas { width: 720px; height: 540px; background: #000; }
.controls label { display: block; margin: 0.4em 0; }
.grid { display: flex; gap: 0.8em; flex-wrap: wrap; }
figure { margin: 0; width: 220px; } figure img { width: 220px; image-rendering: pixelated; border: 1px solid #ccc; }
figcaption { font-size: 0.85em; color: #555; }
table { border-collapse: collapse; font-size: 0.9em; } td { padding: 1px 8px; border-bottom: 1px solid #eee; }
.note { color: #a33; }
"""

CONTROLS = """
<div class="controls">
<label>light azimuth <input id="ntp-light-azimuth" type="range" min="0" max="360" value="30"></label>
<label>light elevation <input id="ntp-light-elevation" type="range" min="-10" max="85" value="35"></label>
<label>exposure (stops) <input id="ntp-exposure" type="range" min="-4" max="4" step="0.1" value="0"></label>
<label><input id="ntp-turntable" type="checkbox"> turntable</label>
<p>drag: orbit · wheel: zoom · right drag: pan</p>
<p id="ntp-viewer-error" class="note"></p>
</div>
"""


def page_html(result: Path, glb: Path | None, bundle: Path = VIEWER_BUNDLE) -> str:
    """The page's HTML for ``result`` with ``glb`` as its asset (``None``: no 3D view)."""
    report_path = result / REPORT_FILE
    try:
        report = json.loads(report_path.read_text())
    except (OSError, ValueError) as err:
        raise NtpInputError(report_path, f"not a complete result's report ({err})") from None
    name = html.escape(result.resolve().name)
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>ntp result: {name}</title>"]
    parts.append(f"<style>{STYLE}</style></head><body><h1>ntp result: {name}</h1>")

    parts.append("<h2>Asset</h2>")
    if glb is not None and bundle.is_file():
        data = json.dumps({"glb": base64.b64encode(glb.read_bytes()).decode("ascii")})
        parts.append(f'<div id="ntp-view"><canvas id="ntp-canvas"></canvas>{CONTROLS}</div>')
        parts.append(f'<script id="ntp-data" type="application/json">{data}</script>')
        script = bundle.read_text().replace("</script", "<\\/script")
        parts.append(f"<script>{script}</script>")
    elif glb is None:
        parts.append(
            f'<p class="note">No asset: make one with <code>{GLB_HOWTO}</code> '
            "(needs bpy), then <code>ntp view RESULT --glb A.glb</code>.</p>"
        )
    else:
        parts.append(
            '<p class="note">The 3D view\'s script is not built: <code>make setup</code> builds it where npm '
            "exists (ntp_engine/pipeline/web).</p>"
        )

    parts.append("<h2>Maps</h2><div class='grid'>")
    for file, caption in MAP_PREVIEWS:
        path = result / "previews" / file
        if path.is_file():
            parts.append(_figure(file_data(path, "image/png"), caption))
    parts.append("</div>")

    parts.append(
        "<h2>Coverage and uncertainty</h2><p>red: measured too little · green: measured well · grey: no surface</p>"
    )
    parts.append("<div class='grid'>")
    for label, src, (bad, good), hint in layer_images(result):
        parts.append(_figure(src, f"{label}: {bad} (red) … {good} (green). {hint}"))
    parts.append("</div>")

    registration = result / "registration.png"
    if registration.is_file():
        parts.append("<h2>Registration</h2>")
        parts.append(f'<img src="{file_data(registration, "image/png")}" style="max-width:100%" alt="registration">')

    parts.append("<h2>Numbers (report.json)</h2><table>")
    for key, text in _numbers(report):
        parts.append(f"<tr><td>{html.escape(key)}</td><td>{html.escape(text)}</td></tr>")
    parts.append("</table></body></html>")
    return "\n".join(parts)


def write_page(result: str | Path, glb: str | Path | None = None) -> Path:
    """Write ``result/index.html`` (atomically) with ``glb`` as its asset (``None``: the page without
    the 3D view, saying how to make one). One-line errors name a missing result or a bad ``.glb``."""
    result = Path(result)
    if not (result / REPORT_FILE).is_file():
        raise NtpInputError(result, f"not an ntp result (no {REPORT_FILE})")
    if glb is not None and not Path(glb).is_file():
        raise NtpInputError(glb, "missing")
    glb_path = None if glb is None else Path(glb)
    if glb_path is not None and glb_path.read_bytes()[:4] != b"glTF":
        raise NtpInputError(glb_path, "not a binary glTF (.glb)")
    out = result / PAGE_FILE
    write_text_atomic(out, page_html(result, glb_path))
    return out
