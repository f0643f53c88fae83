"""From traces to texture maps (the pipeline's core, paper §7); ``pipeline.reconstruct`` runs it.

mesh (+ UVs, else xatlas) -> texels -> traces (trace.py) -> network (inference.py, in bounded
batches) -> geometry fit per batch (fit.py) -> RGB albedo least squares on each texel's own trace
-> shading frame from each texel's geometric frame (n^, t^) into object space -> maps with
unobserved texels filled from their nearest observed neighbour (marked in confidence.exr).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .atomic import write_text_atomic
from .device import Device
from .errors import NtpInputError
from .fit import FLAG_NO_LOBE, GeometryFit, fit_geometry, highlights_and_albedo
from .images import write_exr, write_png
from .inference import RaggedTraces, predict
from .maps import SVBRDFMaps, fill_missing
from .mesh import Mesh, save_obj, smooth_normals
from .scan import Scan
from .texels import Texels


def uv_atlas(mesh: Mesh, resolution: int) -> Mesh:
    """The mesh with xatlas UVs (vertices split at seams); texel density set from the mesh area so
    the atlas fills a ``resolution``^2 map."""
    import xatlas

    atlas = xatlas.Atlas()
    atlas.add_mesh(mesh.vertices.astype(np.float32), mesh.faces.astype(np.uint32))
    pack = xatlas.PackOptions()
    pack.resolution = resolution
    pack.texels_per_unit = 0.8 * resolution / max(np.sqrt(mesh.area()), 1e-9)
    pack.padding = 2
    atlas.generate(pack_options=pack)
    vmap, faces, uv = atlas[0]
    v = mesh.vertices[vmap]
    return Mesh(v, faces.astype(np.int64), uv.astype(np.float64), smooth_normals(v, faces.astype(np.int64)))


ALBEDO_VIEWS = 16  # entries per texel for the beta check and the albedo LS (Eq. 1 per entry and emitter)
RHO_S_PRIOR_WEIGHT = 1.0  # the network's rho_s counts as one view in the albedo LS (fit._albedo_ls)


def fit_traces(net, device: Device, traces: RaggedTraces, pixel_scale: float, batch: int = 4096,
               progress: bool = False) -> dict[str, np.ndarray]:
    """Network + geometry fit + RGB albedo per trace. ``pixel_scale`` is the factor the traces' linear
    pixels were scaled by to the model's exposure (undone for the physical albedo LS). Returns per-trace arrays in the
    texel's geometric frame: n_loc, t_loc (N, 3), alpha (N, 2), flags (N,), rho_d, rho_s (N, 3)."""
    N = traces.num_traces
    n_loc, t_loc = np.zeros((N, 3)), np.zeros((N, 3))
    n_loc[:, 2], t_loc[:, 0] = 1.0, 1.0
    ax, ay, flags = np.full(N, 0.3), np.full(N, 0.3), np.zeros(N, np.int64)
    rho_d, rho_s = np.zeros((N, 3)), np.zeros((N, 3))
    observed = int((traces.lengths > 0).sum())
    bar = tqdm(total=observed, desc="network + fit", unit="texel", disable=not progress)
    for idx, d, s in predict(net, traces, max_entries=batch * 32):
        keep = traces.lengths[idx] > 0
        idx, d, s = idx[keep], d[keep], s[keep]
        if len(idx) == 0:
            continue
        g = fit_geometry(s, d)
        i = idx.numpy()
        n_loc[i], t_loc[i] = g.normal.numpy(), g.tangent.numpy()
        ax[i], ay[i], flags[i] = g.alpha_x.numpy(), g.alpha_y.numpy(), g.flags.numpy()
        for a in range(0, len(idx), 256):  # (n, V, L) Eq. 1 terms: keep them cache-sized
            sub = slice(a, a + 256)
            ent, mask = traces.padded(idx[sub], max_views=ALBEDO_VIEWS)
            gs = GeometryFit(*(None if v is None else v[sub] for v in
                               (g.normal, g.tangent, g.alpha_x, g.alpha_y, g.rho_s, g.flags, g.log_rmse)))
            _, rd, rs = highlights_and_albedo(device, ent[..., :3] / pixel_scale, ent[..., 3:6], ent[..., 6:9],
                                              ent[..., 9:12], mask, gs, prior_weight=RHO_S_PRIOR_WEIGHT)
            rho_d[i[sub]], rho_s[i[sub]] = rd.numpy(), rs.numpy()
            ax[i[sub]], ay[i[sub]], flags[i[sub]] = gs.alpha_x.numpy(), gs.alpha_y.numpy(), gs.flags.numpy()
        bar.update(len(idx))
    bar.close()
    return {"n_loc": n_loc, "t_loc": t_loc, "alpha": np.stack([ax, ay], 1), "flags": flags,
            "rho_d": rho_d, "rho_s": rho_s}


def write_result(out: Path, mesh: Mesh, texels: Texels, fitted: dict[str, np.ndarray], lengths: np.ndarray) -> None:
    """Maps (EXR), confidence, previews, mesh, material.json into ``out`` (each file atomically).
    Texels without a trace keep the geometric frame and get their values from the nearest observed
    texel (seams and holes dilated)."""
    observed = lengths > 0
    frame = np.stack([texels.tangent, np.cross(texels.normal, texels.tangent), texels.normal], 1)  # rows
    n_obj = np.einsum("tji,tj->ti", frame, fitted["n_loc"])
    t_obj = np.einsum("tji,tj->ti", frame, fitted["t_loc"])
    n_obj = np.where(observed[:, None], n_obj, texels.normal)
    t_obj = np.where(observed[:, None], t_obj, texels.tangent)
    H, W = texels.shape
    known = np.zeros((H, W), bool)
    known[texels.row, texels.col] = observed

    def to_map(values: np.ndarray) -> np.ndarray:
        img = np.zeros((H, W, values.shape[1]))
        img[texels.row, texels.col] = values
        return fill_missing(img, known)

    n_map, t_map = to_map(n_obj), to_map(t_obj)
    n_map /= np.maximum(np.linalg.norm(n_map, axis=-1, keepdims=True), 1e-12)
    t_map -= (t_map * n_map).sum(-1, keepdims=True) * n_map
    t_map /= np.maximum(np.linalg.norm(t_map, axis=-1, keepdims=True), 1e-12)
    maps = SVBRDFMaps(to_map(fitted["rho_d"]), to_map(fitted["rho_s"]), n_map, t_map, to_map(fitted["alpha"]))
    out.mkdir(parents=True, exist_ok=True)
    maps.save(out)
    conf = np.zeros((H, W, 3))
    conf[texels.row, texels.col, 0] = observed & ((fitted["flags"] & FLAG_NO_LOBE) == 0)
    conf[texels.row, texels.col, 1] = lengths
    write_exr(out / "confidence.exr", conf)
    previews = out / "previews"
    write_png(previews / "diffuse_albedo.png", maps.diffuse_albedo ** (1 / 2.2))
    write_png(previews / "specular_albedo.png", (maps.specular_albedo / 10) ** (1 / 2.2))
    write_png(previews / "normal.png", 0.5 * (maps.normal + 1))
    write_png(previews / "tangent.png", 0.5 * (maps.tangent + 1))
    write_png(previews / "roughness.png", np.concatenate([maps.roughness / 0.5, np.zeros((H, W, 1))], -1))
    save_obj(out / "mesh.obj", mesh)
    write_text_atomic(out / "material.json", json.dumps({
        "model": "anisotropic GGX (ntp)", "maps": {k: f"{k}.exr" for k in
                                                   ("diffuse_albedo", "specular_albedo", "normal", "tangent",
                                                    "roughness")},
        "conventions": {"normal": "object space, unit", "tangent": "object space, unit, alpha_x along it",
                        "roughness": "R = alpha_x, G = alpha_y", "albedo": "linear", "units": "metres",
                        "fresnel_f0": 0.04, "uv_origin": "bottom-left"}}, indent=2))


def reconstruct_with_poses(scan: Scan, out: Path, resolution: int = 1024, model: str | None = None,
                           progress: bool = False) -> dict:
    """Reconstruct maps for ``scan`` (which must carry poses) into ``out``; returns the report."""
    if scan.poses is None:
        raise NtpInputError(scan.folder / "scan.toml", "no poses: give a poses file")
    from .pipeline import reconstruct

    return reconstruct(scan, out, resolution=resolution, model=model, progress=progress)
