"""Errors of a reconstruction against ground truth (a virtual scan's ``ground_truth/``).

- map errors over the texels some trace reached (``confidence.exr`` G > 0): median angle between
  reconstructed and true normals (degrees), RMSE of the diffuse albedo (linear RGB), coverage;
- relit SSIM: the engine renders the true and the reconstructed asset from novel viewpoints, each
  lit by the point-light device (a novel light: a single point, unlike the LED array of the scan),
  with exact shadows; one display transform for both (the truth's 99th percentile to 1, clip,
  gamma 2.2); SSIM averaged over the object's pixels only (the backdrop would inflate it).

- the given mesh's ceiling (``mesh_ceiling``): the relit SSIM of the truth's own maps on the mesh a
  scan hands ntp in place of the photographed one — what the given geometry alone costs, the bound
  on any result's relit SSIM on that mesh.

- per material (``material_errors``, gallery assets with ``labels.png``): **seen** (the share of the
  material's surface texels — those the result's atlas puts on the mesh — that some photo sees: in
  the image, facing the camera, not hidden by the mesh; ``seen_texels``, from the true poses) and
  **coverage** (the share of the seen ones that some trace reached), normal angle,
  tangent angle mod 180 deg between the axes of the larger alpha (texels whose true anisotropy is
  >= 2:1), |log alpha ratio| of the sorted alphas (larger with larger), rho_d RMSE and ratio (mean
  reconstructed / mean true), **border** (the share of texels on a material border,
  ``material_border``) and the rho_d RMSE of the others (**rho_d_rmse_inside**: where the rho_d
  error lies, not a target), **rho_d_rmse_floor** (the rho_d RMSE of the truth averaged over each
  texel's square, ``texel_means``: what a perfect map at the result's resolution scores, its
  border texels holding the mean of two materials; not a target), |log rho_s ratio| (channel
  means), and on matte materials the spurious-lobe rate: the fraction of texels given rho_s >
  ``SPURIOUS_RHO_S``. Medians over the material's observed texels (the truth at each texel's
  centre, ``truth_at_texels``); NaN where a metric does not apply or nothing was observed.

Both assets must share the UV layout (true for scans of a mesh with UVs, whose UVs the pipeline
keeps).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from skimage.metrics import structural_similarity

from ..io.images import read_image, write_png
from ..io.maps import MAP_FILES, SVBRDFMaps, bilinear, bilinear_corners, bilinear_weights, texel_uv, uv_to_pixel
from ..io.mesh import Mesh, load_mesh
from ..io.raycast import RayCaster
from ..io.texels import rasterize
from ..register.align import camera_similarity, moved_pose
from ..scanner.camera import in_image, project, resampled
from ..scanner.device_file import shipped_device
from ..scanner.scanner import Scanner
from .materials import load_labels
from .renderer import Scene
from .virtual_scan import ScanConfig, trajectory

SPURIOUS_RHO_S = 0.1  # a matte texel given more specular albedo than this has a spurious lobe
MIN_ANISOTROPY = 2.0  # tangents are scored where the true alphas differ by at least this ratio
NOVEL_LIGHT_DEVICE = "point_light.toml"  # relit under a single point light, unlike the scan's LED array
# the groups of maps ``relit_budget`` replaces by the truth, one at a time
BUDGET_GROUPS = {
    "diffuse": ("diffuse_albedo",),
    "normal": ("normal",),
    "lobe": ("specular_albedo", "roughness"),
    "tangent": ("tangent",),
    "everything": tuple(MAP_FILES),
}


def map_errors(result: Path, truth: Path) -> dict:
    """Normal angle (median, p90; degrees), diffuse RMSE and the observed fraction of a result's
    maps against the truth's, over the texels some trace reached."""
    rec = SVBRDFMaps.load(result)
    H, W = rec.normal.shape[:2]
    observed = read_image(result / "confidence.exr")[..., 1].reshape(-1) > 0
    g = SVBRDFMaps.load(truth).sample(texel_uv((H, W)).reshape(-1, 2))
    ang = _angle_deg(rec.normal.reshape(-1, 3)[observed], g["normal"][observed])
    d = rec.diffuse_albedo.reshape(-1, 3)[observed] - g["diffuse_albedo"][observed]
    return {
        "normal_median_deg": float(np.median(ang)),
        "normal_p90_deg": float(np.percentile(ang, 90)),
        "diffuse_rmse": float(np.sqrt((d**2).mean())),
        "observed_fraction": float(observed.mean()),
    }


def _angle_deg(a: np.ndarray, b: np.ndarray, axial: bool = False) -> np.ndarray:
    c = (a * b).sum(-1)
    return np.degrees(np.arccos(np.clip(np.abs(c) if axial else c, -1, 1)))


def _nearest(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """The texel of ``img (H, W, C)`` containing each ``uv (N, 2)``: ``(N, C)``."""
    h, w = img.shape[:2]
    return img[np.clip(((1 - uv[:, 1]) * h).astype(int), 0, h - 1), np.clip((uv[:, 0] * w).astype(int), 0, w - 1)]


# the per-material metrics of the observed texels (module docstring), NaN where one does not apply
PARAMETER_METRICS = (
    "normal_deg",
    "tangent_deg",
    "log_alpha",
    "rho_d_rmse",
    "rho_d_ratio",
    "border",
    "rho_d_rmse_inside",
    "rho_d_rmse_floor",
    "log_rho_s",
    "spurious_lobe",
)


def truth_at_texels(truth: SVBRDFMaps, labels: np.ndarray, uv: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The truth where the renderer shades a result's texel centres ``uv (N, 2)``: each map's
    bilinear sample ``(N, C)`` (normal unit, tangent orthogonal to it) over only the truth texels of
    the centre's own material — the label of the truth texel containing it, also returned ``(N,)``
    — so materials do not blend at borders. Where the result's texels are the truth's (same
    resolution) that is the texel itself; where the truth is finer, a texel centre lies between truth
    texels, and the one containing it (its nearest) is half a truth texel off: on the gallery's
    curved objects 1-2 deg of normal (docs/history/accuracy.md)."""
    label = _nearest(labels[..., None], uv)[:, 0]
    return truth.sample(uv, _own_material_taps(labels, uv, label)[0]), label


def _own_material_taps(labels: np.ndarray, uv: np.ndarray, label: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which of the four truth texels a bilinear sample at ``uv (N, 2)`` reads (``bilinear_corners``'
    order) hold the centre's own ``label (N,)`` ``(N, 4)`` bool (the containing texel always one),
    and their bilinear weights ``(N, 4)``."""
    h, w = labels.shape
    rows, cols, fr, fc = bilinear_corners(h, w, *uv_to_pixel(uv, (h, w)))
    return labels[rows, cols] == label[:, None], bilinear_weights(fr, fc)


def texel_means(truth: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A map ``truth (Ht, Wt, C)`` averaged over each texel's square of a ``shape (H, W)`` grid:
    ``(H W, C)`` in row-major order (``texel_uv``'s), from n x n bilinear samples per texel, n per
    axis the ceiling of truth / grid texels (exact where the truth is n times finer: the samples land
    on its texel centres)."""
    H, W = shape
    n_v, n_u = -(-truth.shape[0] // H), -(-truth.shape[1] // W)
    uv = texel_uv(shape).reshape(-1, 2)
    out = np.zeros((len(uv), truth.shape[2]))
    for i in range(n_u):
        for j in range(n_v):
            step = np.array([((i + 0.5) / n_u - 0.5) / W, ((j + 0.5) / n_v - 0.5) / H])
            out += bilinear(truth, uv + step)
    return out / (n_u * n_v)


def material_border(labels: np.ndarray, uv: np.ndarray, label: np.ndarray) -> np.ndarray:
    """Whether a result texel centred at ``uv (N, 2)`` straddles a material border: ``(N,)`` bool,
    True where the bilinear sample at its centre weighs a truth texel of another material than the
    centre's ``label (N,)`` (a result as fine as the truth: never). Its photos see both materials
    there and the texel holds one value: its rho_d comes out between them, scored against its
    centre's material (docs/history/accuracy.md, "Texels on a material border")."""
    own, weight = _own_material_taps(labels, uv, label)
    return (~own & (weight > 0)).any(1)


def _major_axis(maps: dict[str, np.ndarray]) -> np.ndarray:
    """Unit direction of the larger alpha ``(N, 3)`` (the tangent, or n x t when alpha_y is larger)."""
    t, n, a = maps["tangent"], maps["normal"], maps["roughness"]
    return np.where((a[:, 0] >= a[:, 1])[:, None], t, np.cross(n, t))


def parameter_errors(rec: dict[str, np.ndarray], true: dict[str, np.ndarray], matte: bool) -> dict[str, float]:
    """The per-material metrics (module docstring) of texels of one material: reconstructed and true
    maps as ``{map name: (N, C)}`` (object space), the truth's labels saying whether it is matte."""
    out = {
        "normal_deg": float(np.median(_angle_deg(rec["normal"], true["normal"]))),
        "rho_d_rmse": float(np.sqrt(((rec["diffuse_albedo"] - true["diffuse_albedo"]) ** 2).mean())),
        "rho_d_ratio": float(rec["diffuse_albedo"].mean() / max(true["diffuse_albedo"].mean(), 1e-12)),
    }
    rs_rec = rec["specular_albedo"].mean(1)
    if matte:
        out["spurious_lobe"] = float((rs_rec > SPURIOUS_RHO_S).mean())
        return out
    ra, ta = np.sort(rec["roughness"][:, :2], 1), np.sort(true["roughness"][:, :2], 1)
    out["log_alpha"] = float(np.median(np.abs(np.log(np.maximum(ra, 1e-6) / ta))))
    rs_true = true["specular_albedo"].mean(1)
    lobe = rs_true > 0  # texels pooled over materials (the refine bench's baseline) may hold matte ones
    ratio = np.maximum(rs_rec[lobe], 1e-3) / rs_true[lobe]
    out["log_rho_s"] = float(np.median(np.abs(np.log(ratio)))) if lobe.any() else float("nan")
    aniso = ta[:, 1] >= MIN_ANISOTROPY * ta[:, 0]
    if aniso.any():
        rec_axis = _major_axis({key: v[aniso] for key, v in rec.items()})
        true_axis = _major_axis({key: v[aniso] for key, v in true.items()})
        out["tangent_deg"] = float(np.median(_angle_deg(rec_axis, true_axis, axial=True)))
    return out


def surface_texels(mesh: Mesh, shape: tuple[int, int]) -> np.ndarray:
    """Which texels of maps of ``shape`` the atlas of ``mesh`` puts on the surface: ``(H W,)`` bool
    in the maps' row-major order (a chart's gutter and the space between charts are not)."""
    tex = rasterize(mesh, shape)
    on = np.zeros(shape[0] * shape[1], bool)
    on[tex.row * shape[1] + tex.col] = True
    return on


def seen_texels(mesh: Mesh, shape: tuple[int, int], scanner: Scanner, poses: list[np.ndarray]) -> np.ndarray:
    """Which surface texels (``surface_texels``) some photo sees: the texel centre projects into the
    image from in front of the camera at ``poses`` (camera-from-mesh, 4x4), its surface faces the
    camera and no part of the mesh lies between. Geometry only, and none of the traces stage's own
    thresholds (grazing views, the valid volume, shadows): the texels a scan could have measured.
    ``(H W,)`` bool in the maps' order."""
    tex = rasterize(mesh, shape)
    caster = RayCaster([mesh.triangles])
    eps = 1e-4 * float(np.ptp(mesh.vertices, 0).max())  # off the surface: the texel's own face
    origin = tex.position + eps * tex.normal
    seen = np.zeros(len(tex), bool)
    for pose in poses:
        R, t = pose[:3, :3], pose[:3, 3]
        x = tex.position @ R.T + t
        px = project(scanner, torch.as_tensor(x)).numpy()  # NaN behind the camera
        # a face turned away is hidden anyway (the offset ray meets it): the test only spares rays
        facing = in_image(scanner, px) & ((-x * (tex.normal @ R.T)).sum(1) > 0)
        idx = np.nonzero(facing & ~seen)[0]
        to_cam = -R.T @ t - origin[idx]
        dist = np.linalg.norm(to_cam, axis=1)
        seen[idx[~caster.occluded(origin[idx], to_cam / dist[:, None], dist)]] = True
    out = np.zeros(shape[0] * shape[1], bool)
    out[tex.row * shape[1] + tex.col] = seen
    return out


def material_errors(
    result: Path, truth: Path, scanner: Scanner | None = None, poses: list[np.ndarray] | None = None
) -> list[dict]:
    """Errors per labelled material of a result against a gallery ground truth (module docstring):
    one dict per material in label order. ``seen`` and ``coverage`` count the result's surface
    texels (its ``mesh.obj``'s atlas) and, given the ``scanner`` and the true ``poses`` of the scan,
    those some photo sees (``seen_texels``); without them every surface texel counts as seen."""
    rec_maps = SVBRDFMaps.load(result)
    shape = rec_maps.shape
    uv = texel_uv(shape).reshape(-1, 2)
    observed = read_image(result / "confidence.exr")[..., 1].reshape(-1) > 0
    mesh = load_mesh(result / "mesh.obj")
    surface = surface_texels(mesh, shape)
    seen = surface if scanner is None or poses is None else seen_texels(mesh, shape, scanner, poses)
    labels, table = load_labels(truth)
    truth_maps = SVBRDFMaps.load(truth)
    true, label = truth_at_texels(truth_maps, labels, uv)
    border = material_border(labels, uv, label)
    ideal = texel_means(truth_maps.diffuse_albedo, shape)  # the best rho_d map at this resolution
    rec = {k: getattr(rec_maps, k).reshape(-1, getattr(rec_maps, k).shape[-1]) for k in MAP_FILES}
    rows = []
    for k, mat in enumerate(table):
        member = (label == k) & surface
        sel = member & observed
        row: dict = {
            "material": mat["name"],
            "kind": mat.get("kind"),  # Material.kind (older assets' tables lack it)
            "texels": int(member.sum()),
            "seen": float((member & seen).sum() / max(member.sum(), 1)),
            "coverage": float((sel & seen).sum() / max((member & seen).sum(), 1)),
        }
        row.update(dict.fromkeys(PARAMETER_METRICS, float("nan")))
        if sel.any():
            rec_sel = {key: v[sel] for key, v in rec.items()}
            row.update(parameter_errors(rec_sel, {key: v[sel] for key, v in true.items()}, mat["matte"]))
            # where its rho_d error lies: texels on a material border (a diagnostic; the target is rho_d_rmse)
            row["border"] = float(border[sel].mean())
            row["rho_d_rmse_floor"] = float(np.sqrt(((ideal[sel] - true["diffuse_albedo"][sel]) ** 2).mean()))
            inside = sel & ~border
            if inside.any():
                err = rec["diffuse_albedo"][inside] - true["diffuse_albedo"][inside]
                row["rho_d_rmse_inside"] = float(np.sqrt((err**2).mean()))
        rows.append(row)
    return rows


def compare_images(reference: np.ndarray, test: np.ndarray, mask: np.ndarray) -> dict:
    """SSIM and PSNR of two linear renders ``(H, W, 3)`` over ``mask`` pixels, after one display
    transform for both: scaled so the reference's 99th percentile is 1, clipped, gamma 2.2 (no
    saturated plateau hides differences). SSIM is the mean of the SSIM map over the mask."""
    k = 1.0 / max(float(np.percentile(reference[mask], 99)), 1e-12)
    da, db = (np.clip(x * k, 0, 1) ** (1 / 2.2) for x in (reference, test))
    da[~mask], db[~mask] = 0, 0
    _, smap = structural_similarity(da, db, data_range=1.0, channel_axis=-1, full=True)
    mse = float(((da - db)[mask] ** 2).mean())
    return {
        "ssim": float(smap.mean(-1)[mask].mean()),
        "psnr_db": float(10 * np.log10(1.0 / max(mse, 1e-12))),
        "display": (da, db),
    }


def _novel_views(true_scene: Scene, lights: int, scale: float, seed: int) -> list[tuple]:
    """The ``lights`` novel views of the relit comparison: (pose, camera, the truth's render, its
    object pixels) each."""
    point = true_scene.scanner
    cam = resampled(point, scale)
    poses = trajectory(true_scene.center, point, ScanConfig(views=lights, seed=seed), np.random.default_rng(seed))
    views = []
    for pose in poses:
        a, ha = true_scene.render_linear(pose, cam, exact_shadows=True)
        views.append((pose, cam, a, (ha["geom"] == 0).reshape(a.shape[:2])))
    return views


def _relit_scene(mesh: Mesh, maps: SVBRDFMaps) -> Scene:
    """``mesh`` with ``maps`` lit by the relit comparison's point-light device."""
    return Scene(mesh, maps, shipped_device(NOVEL_LIGHT_DEVICE), clusters=1)


def _relit_scores(scene: Scene, views: list[tuple], save_dir: Path | None = None) -> list[float]:
    """SSIM of ``scene``'s render against the truth's in each of ``views`` (``_novel_views``)."""
    scores = []
    for k, (pose, cam, a, obj) in enumerate(views):
        b, _ = scene.render_linear(pose, cam, exact_shadows=True)
        c = compare_images(a, b, obj)
        scores.append(c["ssim"])
        if save_dir is not None:
            write_png(save_dir / f"relit_{k}.png", np.concatenate(c["display"], 1))
    return scores


def relit_ssim(
    result: Path,
    truth_mesh: Path,
    truth_maps: Path,
    lights: int = 3,
    scale: float = 0.25,
    seed: int = 1000,
    save_dir: Path | None = None,
) -> dict:
    """Mean SSIM over ``lights`` novel views, each lit by the point-light device, of the result
    rendered against the truth (object pixels; see the module docstring). ``save_dir`` gets the
    pairs as PNG (truth left)."""
    views = _novel_views(_relit_scene(load_mesh(truth_mesh), SVBRDFMaps.load(truth_maps)), lights, scale, seed)
    scores = _relit_scores(_relit_scene(load_mesh(result / "mesh.obj"), SVBRDFMaps.load(result)), views, save_dir)
    return {"relit_ssim": float(np.mean(scores)), "relit_ssim_per_light": scores}


def mesh_ceiling(
    given_mesh: Path,
    truth_mesh: Path,
    truth_maps: Path,
    lights: int = 3,
    scale: float = 0.25,
    seed: int = 1000,
) -> float:
    """What any maps can score on ``given_mesh`` (the mesh a scan hands ntp in place of the
    photographed ``truth_mesh``; the same UV layout): ``relit_ssim`` of the truth's own maps rendered
    on it, at the truth's resolution. Below 1 by what the given mesh's geometry alone changes in the
    renders — where its shadows fall, where its silhouette lies —, the maps' shading normals being
    the truth's; 1.0 for the photographed mesh itself."""
    given = load_mesh(given_mesh)
    if given.uv is None:  # before the truth's renders: nothing to compare them with
        raise ValueError(f"{given_mesh}: no UVs, so the truth's maps cannot lie on it")
    truth = SVBRDFMaps.load(truth_maps)
    views = _novel_views(_relit_scene(load_mesh(truth_mesh), truth), lights, scale, seed)
    return float(np.mean(_relit_scores(_relit_scene(given, truth), views)))


def relit_budget(
    result: Path,
    truth_mesh: Path,
    truth_maps: Path,
    lights: int = 3,
    scale: float = 0.25,
    seed: int = 1000,
) -> dict:
    """Where a result's relit SSIM is lost (``relit_ssim``'s views and lights): the SSIM gained when
    one group of maps (``BUDGET_GROUPS``) of one labelled material's texels — or of all texels —
    is replaced by the truth at the texel centres (``truth_at_texels``), everything else the
    result's. ``{"relit_ssim": as is, "ceiling": every map the truth's (the result's resolution's
    own limit), "materials": [{"material": name, group: gain, ...}, ..., {"material": "all", ...}]}``.
    Gains of one material's groups need not add up: SSIM is not additive."""
    labels, table = load_labels(truth_maps)
    truth = SVBRDFMaps.load(truth_maps)
    views = _novel_views(_relit_scene(load_mesh(truth_mesh), truth), lights, scale, seed)
    rec = SVBRDFMaps.load(result)
    shape = rec.shape
    true, label = truth_at_texels(truth, labels, texel_uv(shape).reshape(-1, 2))
    scene = _relit_scene(load_mesh(result / "mesh.obj"), rec)

    def ssim_with_truth(where: np.ndarray, names: tuple[str, ...]) -> float:
        maps = {k: getattr(rec, k).reshape(-1, getattr(rec, k).shape[-1]).copy() for k in MAP_FILES}
        for k in names:
            swapped = true[k][where]
            if k == "tangent":  # an axis: the truth's sign turned to the (signed) result's, texel by
                # texel, or a swapped material's boundary would hold opposed neighbours (``consistent_axes``)
                swapped = swapped * np.where((swapped * maps[k][where]).sum(-1, keepdims=True) < 0, -1.0, 1.0)
            maps[k][where] = swapped
        scene.maps = SVBRDFMaps(**{k: v.reshape(*shape, -1) for k, v in maps.items()})
        return float(np.mean(_relit_scores(scene, views)))

    everywhere = np.ones(len(label), bool)
    as_is = ssim_with_truth(everywhere, ())
    rows = []
    for name, where in [(m["name"], label == k) for k, m in enumerate(table)] + [("all", everywhere)]:
        row: dict = {"material": name}
        for group, names in BUDGET_GROUPS.items():
            row[group] = ssim_with_truth(where, names) - as_is
        rows.append(row)
    return {"relit_ssim": as_is, "ceiling": as_is + rows[-1]["everything"], "materials": rows}


def pose_error(poses: dict[str, np.ndarray], truth: dict[str, np.ndarray]) -> dict:
    """Median / max camera-centre distance (m) and rotation angle (deg) of camera-from-world
    ``poses`` against the true ones, over the photos both have; empty if none."""
    dt, dr = [], []
    for n, m in poses.items():
        if n not in truth:
            continue
        g = truth[n]
        dt.append(np.linalg.norm(m[:3, :3].T @ m[:3, 3] - g[:3, :3].T @ g[:3, 3]))
        dr.append(np.degrees(np.arccos(np.clip((np.trace(m[:3, :3] @ g[:3, :3].T) - 1) / 2, -1, 1))))
    if not dt:
        return {}
    return {
        "centre_median_m": float(np.median(dt)),
        "centre_max_m": float(np.max(dt)),
        "rotation_median_deg": float(np.median(dr)),
        "rotation_max_deg": float(np.max(dr)),
    }


def turned_about(centre: np.ndarray, turn_deg: float) -> np.ndarray:
    """The 4x4 turn by ``turn_deg`` about the vertical (world z) through ``centre``."""
    a = np.radians(turn_deg)
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    S = np.eye(4)
    S[:3, :3], S[:3, 3] = R, centre - R @ centre
    return S


def pose_error_modulo(
    poses: dict[str, np.ndarray], truth: dict[str, np.ndarray], centre: np.ndarray, turns_deg: list[float] | None
) -> dict:
    """``pose_error`` against the truth's nearest placement under the mesh's symmetries: the turns
    ``turns_deg`` about the vertical through ``centre`` (world), 0 included; ``None``: every turn (a
    body of revolution; searched to 0.01 deg). A symmetric mesh under a turned placement is the same
    asset, so the photos' poses are right if they are right for any of them (``P @ S``: the camera
    sees the turned mesh where it saw the mesh). Adds ``symmetry_turn_deg``, the placement chosen."""

    def err(turn: float) -> dict:
        S = turned_about(centre, turn)
        return pose_error(poses, {n: m @ S for n, m in truth.items()})

    if turns_deg is None:
        grid = np.arange(-180.0, 180.0, 1.0)
        best = float(grid[np.argmin([err(t).get("rotation_median_deg", np.inf) for t in grid])])
        for step in (0.1, 0.01):
            fine = best + np.arange(-10, 11) * step
            best = float(fine[np.argmin([err(t).get("rotation_median_deg", np.inf) for t in fine])])
        candidates = [best]
    else:
        candidates = [0.0, *turns_deg]
    scored = [(err(t), t) for t in candidates]
    out, turn = min(scored, key=lambda e: e[0].get("rotation_median_deg", np.inf))
    return {**out, "symmetry_turn_deg": turn} if out else {}


def similarity_fit(
    poses: dict[str, np.ndarray], truth: dict[str, np.ndarray], scale: bool = True
) -> dict[str, np.ndarray]:
    """``poses`` (camera-from-world in an arbitrary frame and scale) moved by the similarity that best
    fits their camera centres to the true ones (Umeyama, least squares): what is left of their
    error once the 7 degrees of freedom no photo can know are taken out — SfM's own error. Without
    ``scale``, a rigid motion (6 degrees of freedom): metric poses' own error (the board's)."""
    fit = camera_similarity(poses, truth, scale)
    if fit is None:
        return {}
    return {n: moved_pose(poses[n], *fit) for n in poses if n in truth}
