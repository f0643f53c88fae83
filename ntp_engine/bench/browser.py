"""``ntp bench browser``: a result's ``.glb`` drawn by three.js in a real, headless Chromium (the
result page's viewer, ``pipeline/web``) against the engine's own render of the same result, under
the same camera and point light — what a conforming glTF viewer shows of ntp's materials.

The views are the relit evaluation's novel views (``sim.evaluate``); the light is the point-light
device's emitter made isotropic (three.js' ``PointLight`` has no angular falloff; the engine's
device file says cosine) — so light, camera and pixel grid are the same on both sides. The relight
rig's area lights are not used: three.js' ``RectAreaLight`` draws an isotropic lobe (its LTC tables
know no anisotropy), so it could not show the materials ntp exists for. Neither side draws shadows
(a .glb carries none; three.js draws them only from shadow maps a page opts into, with their own
bias): the check is of the materials. Compared on object pixels (the engine's, one pixel in from
the silhouette, where one sample per pixel on each side disagrees): SSIM after
``sim.evaluate.compare_images``' display transform, and the ratio of mean linear colours.
"""

from __future__ import annotations

import argparse
import base64
import dataclasses
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy.ndimage import binary_erosion

from ..io.blender_process import GLB_HOWTO
from ..io.errors import NtpInputError
from ..io.images import write_png
from ..io.maps import SVBRDFMaps
from ..io.mesh import load_mesh
from ..pipeline.result_page import VIEWER_BUNDLE, page_html
from ..scanner.camera import resampled
from ..scanner.device_file import shipped_device
from ..scanner.scanner import Scanner
from ..sim.evaluate import NOVEL_LIGHT_DEVICE, compare_images
from ..sim.renderer import Scene
from ..sim.virtual_scan import ScanConfig, trajectory

# three.js' departures from ntp's BRDF that a .glb cannot turn off, each as a text replacement in
# three.js' shader chunks (r187), for ``--without`` to measure what each costs
ABLATIONS = {
    # specular anti-aliasing: roughness += the screen-space change of the geometric normal
    "specular-aa": ("lights_physical_fragment", "material.roughness += geometryRoughness;", ""),
    # multiple-scattering energy compensation of the specular lobe (ntp's GGX has single scattering)
    "multiscatter": (
        "lights_physical_pars_fragment",
        "irradiance * specularBRDF * material.multiScatteringCompensation",
        "irradiance * specularBRDF",
    ),
}
HELP = "a result's .glb in headless Chromium (three.js) vs the engine's render: SSIM, mean colour"
CHECK_SCRIPT = Path(__file__).resolve().parent.parent / "pipeline" / "web" / "check.mjs"
# ``make setup`` installs the pinned npm packages (three, esbuild, playwright-core) into .venv/node
NODE_MODULES = Path(os.environ.get("NTP_NODE_MODULES", Path(sys.prefix) / "node" / "node_modules"))


def chromium() -> str | None:
    """The Chromium the check drives (``NTP_CHROMIUM``, else Debian's ``chromium`` on the PATH)."""
    return os.environ.get("NTP_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")


def unavailable() -> str | None:
    """Why the browser check cannot run here (one line), or ``None`` when it can."""
    if shutil.which("node") is None:
        return "node is not installed"
    if not (NODE_MODULES / "playwright-core").is_dir():
        return f"playwright-core is not in {NODE_MODULES} (make setup installs it where npm exists)"
    if not VIEWER_BUNDLE.is_file():
        return f"the viewer bundle {VIEWER_BUNDLE} is not built (make setup builds it where npm exists)"
    if chromium() is None:
        return "Chromium is not installed (Debian: apt-get install chromium; make setup does it as root)"
    return None


def run_page(page: Path, job: dict, out: Path, timeout: float = 600.0) -> dict:
    """Load ``page`` in headless Chromium and run ``job`` (``check.mjs``); its ``result.json``."""
    job = {"chromium": chromium(), **job}
    out.mkdir(parents=True, exist_ok=True)
    (out / "job.json").write_text(json.dumps(job))
    env = {**os.environ, "NTP_NODE_MODULES": str(NODE_MODULES)}
    proc = subprocess.run(
        ["node", str(CHECK_SCRIPT), str(page), str(out / "job.json"), str(out)],
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    path = out / "result.json"
    if not path.is_file():
        raise RuntimeError(f"the browser check wrote nothing: {proc.stderr.strip()[-500:]}")
    result = json.loads(path.read_text())
    result["returncode"] = proc.returncode
    return result


def isotropic_point_light() -> Scanner:
    """The point-light device with its emitter made isotropic (three.js' PointLight)."""
    return dataclasses.replace(shipped_device(NOVEL_LIGHT_DEVICE), angular_exponent=0.0)


def view_specs(
    scene: Scene, views: int, scale: float, seed: int, without: tuple[str, ...] = ()
) -> list[tuple[dict, Scanner]]:
    """(renderLinear spec, camera) for ``views`` novel views of ``scene``'s object, three.js drawing
    without the ``ABLATIONS`` named in ``without``."""
    cam = resampled(scene.scanner, scale)
    poses = trajectory(scene.center, scene.scanner, ScanConfig(views=views, seed=seed), np.random.default_rng(seed))
    intensity = scene.exposure * scene.cluster_drive[0]  # one emitter, quadrature weight 1
    out = []
    for pose in poses:
        R, t = pose[:3, :3], pose[:3, 3]
        light_w = R.T @ (scene.scanner.emitter_positions[0] - t)
        spec: dict = {
            "width": cam.width,
            "height": cam.height,
            "fx": float(cam.K[0, 0]),
            "fy": float(cam.K[1, 1]),
            "cx": float(cam.K[0, 2]),
            "cy": float(cam.K[1, 2]),
            "pose": [float(v) for v in pose.reshape(-1)],
            "light": {"position": [float(v) for v in light_w], "intensity": [float(v) for v in intensity]},
            "patches": [list(ABLATIONS[name]) for name in without],
        }
        out.append((spec, cam))
    return out


def decode_view(view: dict) -> np.ndarray:
    """``renderLinear``'s answer as linear RGB ``(H, W, 3)``."""
    rgba = np.frombuffer(base64.b64decode(view["rgba"]), np.float32)
    return rgba.reshape(view["height"], view["width"], 4)[..., :3].astype(np.float64)


def browser_check(
    result: Path,
    glb: Path,
    views: int = 2,
    scale: float = 0.25,
    seed: int = 1000,
    save_dir: Path | None = None,
    without: tuple[str, ...] = (),
) -> dict:
    """Scores of ``glb`` drawn in Chromium against the engine's render of ``result``:
    ``{"ssim": mean, "ssim_per_view": [...], "colour_ratio": (3,) browser / engine mean linear colour
    over the views' object pixels}``; ``without``: three.js ``ABLATIONS`` turned off. ``save_dir`` gets each view as PNG
    (engine left, browser right)."""
    why = unavailable()
    if why:
        raise RuntimeError(f"the browser check cannot run: {why}")
    if not glb.is_file():
        raise NtpInputError(glb, "missing")
    scene = Scene(load_mesh(result / "mesh.obj"), SVBRDFMaps.load(result), isotropic_point_light(), clusters=1)
    specs = view_specs(scene, views, scale, seed, without)
    with tempfile.TemporaryDirectory(prefix="ntp-browser-") as tmp:
        page = Path(tmp) / "index.html"
        page.write_text(page_html(result, glb))
        answer = run_page(page, {"views": [s for s, _ in specs]}, Path(tmp) / "out")
    if answer["returncode"] or answer["page_errors"] or not answer["views"]:
        raise RuntimeError(f"the page failed in Chromium: {(answer['page_errors'] + answer['console_errors'])[:3]}")
    scores, sums = [], np.zeros((2, 3))
    for k, ((spec, cam), view) in enumerate(zip(specs, answer["views"], strict=True)):
        engine, hits = scene.render_linear(np.array(spec["pose"]).reshape(4, 4), cam, shadows=False)
        obj = binary_erosion((hits["geom"] == 0).reshape(engine.shape[:2]))
        browser = decode_view(view)
        c = compare_images(engine, browser, obj)
        scores.append(c["ssim"])
        sums += [engine[obj].sum(0), browser[obj].sum(0)]
        if save_dir is not None:
            write_png(save_dir / f"browser_{k}.png", np.concatenate(c["display"], 1))
    return {
        "ssim": float(np.mean(scores)),
        "ssim_per_view": scores,
        "colour_ratio": [float(v) for v in sums[1] / np.maximum(sums[0], 1e-30)],
        "console_errors": answer["console_errors"],
    }


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``ntp bench browser``'s options."""
    parser.add_argument("result", type=Path, help="a result folder")
    parser.add_argument("--glb", type=Path, required=True, help=f"the asset ({GLB_HOWTO})")
    parser.add_argument("--views", type=int, default=2)
    parser.add_argument("--scale", type=float, default=0.25, help="of the point-light device's 2448x2048 image")
    parser.add_argument("--out", type=Path, default=None, help="a folder for the side-by-side PNGs")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument(
        "--without",
        nargs="*",
        default=[],
        choices=sorted(ABLATIONS),
        help="three.js departures from ntp's BRDF to turn off",
    )


def command(args: argparse.Namespace) -> int:
    """``ntp bench browser``: print the scores; 2 when the check cannot run here."""
    glb = args.glb
    why = unavailable()
    if why:
        print(f"ntp bench browser: cannot run: {why}", file=sys.stderr)
        return 2
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
    scores = browser_check(args.result, glb, args.views, args.scale, save_dir=args.out, without=tuple(args.without))
    ratio = ", ".join(f"{v:.3f}" for v in scores["colour_ratio"])
    per = " ".join(f"{v:.3f}" for v in scores["ssim_per_view"])
    print(f"{glb}: SSIM {scores['ssim']:.4f} ({per}); mean colour browser / engine {ratio}")
    if args.json:
        args.json.write_text(json.dumps(scores, indent=1))
    return 0
