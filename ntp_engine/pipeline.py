"""``ntp reconstruct``: a scan folder to texture maps, stage by stage, each stage cached under
``OUT/cache`` (DESIGN.md data flow):

select (blur, unreadable) -> register (pycolmap SfM + similarity to the mesh; skipped with poses)
-> atlas (mesh UVs, else xatlas) -> traces (Embree visibility, projection, validity)
-> fit (network in bounded batches + fitter) -> maps, report.json.

Each stage's key holds its inputs and the previous stage's key, so a changed option recomputes
from the first stage it affects; an interrupted run resumes from the last finished stage.
"""
from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import numpy as np
import torch

from . import models
from .align import align_to_mesh
from .atomic import write_text_atomic
from .cache import StageCache, digest, file_key
from .errors import NtpInputError
from .inference import RaggedTraces
from .mesh import load_mesh, save_obj
from .raycast import RayCaster
from .reconstruct import ALBEDO_VIEWS, RHO_S_PRIOR_WEIGHT, fit_traces, uv_atlas, write_result
from .register import MIN_REGISTERED, register
from .scan import Scan, read_photo
from .select import BLUR_MARGIN, Selection, select_photos
from .texels import rasterize
from . import trace


def _pose_error(poses: dict[str, np.ndarray], truth: dict[str, np.ndarray]) -> dict:
    """Median / max camera-centre distance (m) and rotation angle (deg) against reference poses."""
    dt, dr = [], []
    for n, m in poses.items():
        if n not in truth:
            continue
        g = truth[n]
        dt.append(np.linalg.norm(m[:3, :3].T @ m[:3, 3] - g[:3, :3].T @ g[:3, 3]))
        dr.append(np.degrees(np.arccos(np.clip((np.trace(m[:3, :3] @ g[:3, :3].T) - 1) / 2, -1, 1))))
    if not dt:
        return {}
    return {"centre_median_m": float(np.median(dt)), "centre_max_m": float(np.max(dt)),
            "rotation_median_deg": float(np.median(dr)), "rotation_max_deg": float(np.max(dr))}


def _stage_timer(report: dict):
    """``timed(name, t0)`` records a stage's wall seconds since ``t0`` in ``report["stages"]``."""
    def timed(name: str, t0: float) -> None:
        report["stages"][name] = round(time.perf_counter() - t0, 3)

    return timed


def register_scan(scan: Scan, out: Path, blur_margin: float = BLUR_MARGIN, progress: bool = True,
                  reference_poses: dict[str, np.ndarray] | None = None,
                  cache: StageCache | None = None) -> tuple[dict[str, np.ndarray], dict, str]:
    """Stages 1-2 (photo selection, then the poses file or SfM + alignment), cached under
    ``out/cache``. Returns (camera-from-world poses by photo name, report entries, poses key)."""
    cache = cache or StageCache(Path(out) / "cache")
    report: dict = {"stages": {}}
    timed = _stage_timer(report)

    # 1. photo selection
    t0 = time.perf_counter()
    sel_key = {"photos": [file_key(p) for p in scan.photo_paths], "margin": blur_margin,
               "camera": [scan.device.width, scan.device.height]}
    folder, h_sel = cache.get("select", sel_key, lambda d: (d / "selection.json").write_text(json.dumps(
        select_photos(scan.photo_paths, scan.device, blur_margin, progress).to_json(), indent=1)))
    sel = Selection.from_json(json.loads((folder / "selection.json").read_text()))
    timed("select", t0)
    report["photos"] = {"total": len(scan.photo_paths), "kept": len(sel.kept), "blurry": sel.blurry,
                        "unreadable": sel.unreadable}
    if len(sel.kept) < MIN_REGISTERED:
        raise NtpInputError(scan.photos_dir, f"only {len(sel.kept)} sharp, readable photos (need {MIN_REGISTERED})")

    # 2. poses: the poses file, else SfM + alignment to the mesh
    t0 = time.perf_counter()
    mesh_key = {"mesh": file_key(scan.mesh_path)}
    if scan.poses is not None:
        poses = {n: scan.poses[n] for n in sel.kept if n in scan.poses}
        reg_info = {"source": "poses file", "unregistered": [n for n in sel.kept if n not in scan.poses]}
        h_pose = digest({n: m.round(9).tolist() for n, m in poses.items()})
    else:
        def run_sfm(d: Path) -> None:
            reg = register(scan.photos_dir, sel.kept, scan.device, d / "sfm", progress=progress)
            names = sorted(reg.poses)
            try:
                al = align_to_mesh(reg.points, [reg.poses[n] for n in names], load_mesh(scan.mesh_path),
                                   float(np.linalg.norm(scan.device.valid_center)), support_plane=scan.support_plane)
            except ValueError as err:
                raise NtpInputError(scan.mesh_path, f"cannot align the SfM points to this mesh: {err}") from None
            (d / "poses.json").write_text(json.dumps({n: al.camera_from_mesh(reg.poses[n]).tolist() for n in names}))
            (d / "registration.json").write_text(json.dumps({
                "source": "structure from motion", "registered": len(names), "unregistered": reg.unregistered,
                "sfm_points": len(reg.points), "alignment": {
                    "scale": al.scale, "residual_m": al.residual_m, "object_points": al.object_points,
                    "inlier_points": al.kept_points, "support_points": al.support_points}}, indent=1))
            shutil.rmtree(d / "sfm", ignore_errors=True)  # the database is large and not needed again

        folder, h_pose = cache.get("register", {"select": h_sel, **mesh_key, "support": scan.support_plane,
                                                "camera": {"K": scan.device.K, "distortion": scan.device.distortion,
                                                           "valid_center": scan.device.valid_center}}, run_sfm)
        poses = {n: np.array(m) for n, m in json.loads((folder / "poses.json").read_text()).items()}
        reg_info = json.loads((folder / "registration.json").read_text())
    timed("register", t0)
    if reference_poses is not None:
        reg_info["pose_error"] = _pose_error(poses, reference_poses)
    report["registration"] = reg_info
    if not poses:
        raise NtpInputError(scan.photos_dir, "no selected photo has a pose")

    return poses, report, h_pose


def reconstruct(scan: Scan, out: Path, resolution: int = 1024, model: str | None = None,
                blur_margin: float = BLUR_MARGIN, progress: bool = True,
                reference_poses: dict[str, np.ndarray] | None = None) -> dict:
    """Run the pipeline on ``scan`` into ``out``; returns the report (also in ``out/report.json``).
    ``reference_poses`` (e.g. a virtual scan's truth) only adds pose errors to the report."""
    if resolution < 8:
        raise NtpInputError(None, f"--resolution {resolution}: need at least 8")
    out = Path(out)
    cache = StageCache(out / "cache")
    t_all = time.perf_counter()
    report: dict = {"scan": str(scan.folder), "stages": {}}
    timed = _stage_timer(report)

    poses, reg_report, h_pose = register_scan(scan, out, blur_margin, progress, reference_poses, cache)
    report["stages"].update(reg_report.pop("stages"))
    report.update(reg_report)
    mesh_key = {"mesh": file_key(scan.mesh_path)}

    # 3. UV atlas + texels
    t0 = time.perf_counter()

    def atlas(d: Path) -> None:
        mesh = load_mesh(scan.mesh_path)
        save_obj(d / "mesh.obj", mesh if mesh.uv is not None else uv_atlas(mesh, resolution))

    folder, h_atlas = cache.get("atlas", {**mesh_key, "resolution": resolution}, atlas)
    mesh = load_mesh(folder / "mesh.obj")
    texels = rasterize(mesh, (resolution, resolution))
    timed("atlas", t0)

    # 4. traces (linear pixels as captured; rescaled to the model's exposure when loaded)
    t0 = time.perf_counter()
    names = sorted(poses)

    def traces_stage(d: Path) -> None:
        photos = (read_photo(scan.photos_dir / n, scan.device).astype(np.uint8) for n in names)
        tr, st = trace.assemble(texels, photos, [poses[n] for n in names], scan.device, RayCaster([mesh.triangles]),
                          progress=progress, support_z=float(mesh.vertices[:, 2].min()) if scan.support_plane else None)
        np.savez(d / "traces.npz", entries=tr.entries.numpy(), offsets=tr.offsets.numpy())
        (d / "stats.json").write_text(json.dumps({"entries": st.entries, "views_used": st.views_used,
                                                  "views_seeing_no_texel": len(names) - st.views_used,
                                                  "rejected": st.rejected}))

    folder, h_tr = cache.get("traces", {"atlas": h_atlas, "poses": h_pose, "support": scan.support_plane,
                                        "max_shadowed_drive": trace.MAX_SHADOWED_DRIVE,
                                        "device": scan.device.to_dict()}, traces_stage)
    net, meta = models.load(model, scan.device)
    scale = net.exposure() / float(scan.device.exposure(scan.device.pattern))
    with np.load(folder / "traces.npz") as z:
        entries = torch.from_numpy(z["entries"])
        entries[:, :3] *= scale
        traces = RaggedTraces(entries, torch.from_numpy(z["offsets"]))
    report["traces"] = json.loads((folder / "stats.json").read_text())
    timed("traces", t0)

    # 5. network + fit
    t0 = time.perf_counter()
    model_key = {"model": str(models.resolve(model)), "summary": meta.get("summary", {})}

    def fit_stage(d: Path) -> None:
        np.savez(d / "fit.npz", **fit_traces(net, scan.device, traces, scale, progress=progress))

    fit_key = {"albedo_views": ALBEDO_VIEWS, "rho_s_prior_weight": RHO_S_PRIOR_WEIGHT}
    folder, _ = cache.get("fit", {"traces": h_tr, **model_key, **fit_key}, fit_stage)
    with np.load(folder / "fit.npz") as z:
        fitted = {k: z[k] for k in z.files}
    timed("network_and_fit", t0)

    # 6. maps
    t0 = time.perf_counter()
    lengths = traces.lengths.numpy()
    write_result(out, mesh, texels, fitted, lengths)
    timed("maps", t0)
    observed = lengths > 0
    report.update({
        "texels": {"total": len(texels), "observed": int(observed.sum()),
                   "coverage": float(observed.mean()) if len(texels) else 0.0,
                   "flagged": int((fitted["flags"] != 0).sum()), "resolution": resolution},
        "model": {"name": model_key["model"], **meta.get("summary", {})},
        "cached_stages": cache.hits, "seconds": round(time.perf_counter() - t_all, 3)})
    report["photos"]["used"] = report["traces"]["views_used"]
    write_text_atomic(out / "report.json", json.dumps(report, indent=2))
    return report
