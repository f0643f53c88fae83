import dataclasses
import shutil

import numpy as np
import pytest

from ntp_engine.io.assets import DEMO_DIR
from ntp_engine.io.errors import NtpInputError
from ntp_engine.io.images import write_exr
from ntp_engine.io.maps import MAP_FILES, SVBRDFMaps, texel_uv
from ntp_engine.io.mesh import Mesh, load_mesh, save_obj, smooth_normals
from ntp_engine.io.texels import rasterize
from ntp_engine.scanner.camera import look_at
from ntp_engine.scanner.device_file import load_scanner
from ntp_engine.sim.evaluate import (
    compare_images,
    material_border,
    material_errors,
    mesh_ceiling,
    parameter_errors,
    pose_error,
    relit_budget,
    relit_ssim,
    seen_texels,
    surface_texels,
    texel_means,
)
from ntp_engine.sim.gallery import build_asset
from ntp_engine.sim.materials import load_labels
from ntp_engine.sim.scanner_mesh import scanner_mesh


def test_identical_renders_score_one_and_differences_lower_it():
    rng = np.random.default_rng(0)
    a = rng.random((24, 32, 3))
    mask = np.zeros((24, 32), bool)
    mask[4:20, 4:28] = True
    same = compare_images(a, a.copy(), mask)
    assert same["ssim"] == pytest.approx(1.0) and same["psnr_db"] > 100
    assert compare_images(a, 0.5 * a, mask)["ssim"] < 0.95


def test_pose_error_in_metres_and_degrees():
    eye = np.eye(4)
    moved = np.eye(4)
    moved[:3, 3] = [0.003, 0.0, 0.004]  # camera centre 5 mm away
    c, s = np.cos(np.radians(2)), np.sin(np.radians(2))
    turned = np.eye(4)
    turned[:2, :2] = [[c, -s], [s, c]]
    err = pose_error({"a": moved, "b": turned, "x": eye}, {"a": eye, "b": eye})
    assert err["centre_max_m"] == pytest.approx(0.005) and err["rotation_max_deg"] == pytest.approx(2.0)
    assert pose_error({"x": eye}, {"a": eye}) == {}


def test_the_truth_relit_against_itself_is_perfect(tmp_path):
    result = tmp_path / "result"
    shutil.copytree(DEMO_DIR / "ground_truth", result)
    shutil.copy(DEMO_DIR / "mesh.obj", result / "mesh.obj")
    r = relit_ssim(result, DEMO_DIR / "mesh.obj", DEMO_DIR / "ground_truth", lights=1, scale=0.05, save_dir=tmp_path)
    assert r["relit_ssim"] == pytest.approx(1.0) and (tmp_path / "relit_0.png").is_file()


def test_the_given_meshs_ceiling_is_perfect_for_the_photographed_mesh_and_falls_with_its_error(tmp_path):
    """The truth's maps on the demo's own mesh score 1; on a scanner's mesh of it (the same UVs, noise
    along the normals) less, and less the noisier it is; a mesh without UVs cannot hold the maps."""
    truth_mesh, truth = DEMO_DIR / "mesh.obj", DEMO_DIR / "ground_truth"
    assert mesh_ceiling(truth_mesh, truth_mesh, truth, lights=1, scale=0.1) == pytest.approx(1.0)
    ceilings = []
    for noise_m in (3e-4, 1e-3):
        given = tmp_path / f"given-{noise_m}.obj"
        save_obj(given, scanner_mesh(load_mesh(truth_mesh), seed=0, noise_m=noise_m))
        ceilings.append(mesh_ceiling(given, truth_mesh, truth, lights=1, scale=0.1))
    assert 1.0 > ceilings[0] > ceilings[1] + 0.05, ceilings
    bare = load_mesh(truth_mesh)
    save_obj(tmp_path / "bare.obj", Mesh(bare.vertices, bare.faces, None, bare.normals))
    with pytest.raises(ValueError, match="no UVs"):
        mesh_ceiling(tmp_path / "bare.obj", truth_mesh, truth, lights=1, scale=0.1)


def _result_from_truth(tmp_path, name="vase", res=32, observed=None):
    asset = build_asset(name, tmp_path / "asset", res)
    result = tmp_path / "result"
    shutil.copytree(asset / "ground_truth", result)
    shutil.copy(asset / "mesh.obj", result / "mesh.obj")
    conf = np.ones((res, res, 3))
    if observed is not None:
        conf[..., 1] = observed
    write_exr(result / "confidence.exr", conf)
    return result, asset / "ground_truth"


def _result_sampled_from_truth(tmp_path, name: str, res: int = 32):
    """A result at half the truth's resolution whose texels hold the truth's bilinear samples at
    their centres (what the renderer shades there), and the truth's folder."""
    asset = build_asset(name, tmp_path / "asset", 2 * res)
    result = tmp_path / "result"
    result.mkdir()
    shutil.copy(asset / "mesh.obj", result / "mesh.obj")
    samples = SVBRDFMaps.load(asset / "ground_truth").sample(texel_uv((res, res)).reshape(-1, 2))
    SVBRDFMaps(*(samples[k].reshape(res, res, -1) for k in MAP_FILES)).save(result)
    write_exr(result / "confidence.exr", np.ones((res, res, 3)))
    return result, asset / "ground_truth"


def test_material_errors_of_the_truth_are_zero(tmp_path):
    result, truth = _result_from_truth(tmp_path)
    rows = material_errors(result, truth)
    assert [r["material"] for r in rows] == ["matte_print", "plastic_glossy", "metal_brushed_dark", "lacquer_mirror"]
    for r in rows:
        assert r["coverage"] == 1 and r["seen"] == 1 and r["normal_deg"] < 0.5 and r["rho_d_rmse"] < 0.05
        assert r["rho_d_ratio"] == pytest.approx(1, abs=0.05)
    matte, _, metal, mirror = rows
    assert matte["spurious_lobe"] == 0 and np.isnan(matte["log_alpha"]) and np.isnan(matte["tangent_deg"])
    assert metal["tangent_deg"] < 1 and metal["log_alpha"] < 0.05 and metal["log_rho_s"] < 0.05
    assert np.isnan(mirror["tangent_deg"])  # isotropic: no tangent to score


def test_the_truth_is_taken_at_each_texels_centre(tmp_path):
    """A result at half the truth's resolution whose texels hold what the renderer shades at their
    centres (the truth's bilinear samples) scores no error in the medians (its albedos blend with
    the neighbouring materials' at borders, as the renderer's do): its centres lie between truth texels,
    and the truth texel containing one is half a truth texel away (on the vase ~1 deg of normal)."""
    result, truth = _result_sampled_from_truth(tmp_path, "vase")
    for r in material_errors(result, truth):
        assert r["normal_deg"] < 0.01, r
        assert np.nan_to_num(r["log_alpha"]) < 0.01 and np.nan_to_num(r["tangent_deg"]) < 0.1


def test_texels_on_a_material_border_are_told_apart(tmp_path):
    """A result at half the truth's resolution holding the truth's bilinear samples: its texels on a
    material border hold a blend of two materials' albedos, scored against their centre's material;
    the others score none. As fine as the truth, no texel is on a border."""
    result, truth = _result_sampled_from_truth(tmp_path, "knot")
    rows = material_errors(result, truth)
    for r in rows:
        assert 0 < r["border"] < 0.5, r
        assert r["rho_d_rmse_inside"] < 1e-5 and r["rho_d_rmse"] > 10 * r["rho_d_rmse_inside"] + 1e-3, r
    labels, _ = load_labels(truth)
    uv = texel_uv(labels.shape).reshape(-1, 2)
    assert not material_border(labels, uv, labels.reshape(-1)).any()
    assert all(r["border"] == 0 for r in material_errors(*_result_from_truth(tmp_path / "same", name="knot")))


def test_the_rho_d_floor_is_what_the_truths_texel_means_score(tmp_path):
    """A result at half the truth's resolution holding the truth averaged over each texel's square
    (the best rho_d map at that resolution) scores exactly its floor, which its texels on a material
    border make > 0; as fine as the truth, the floor is 0."""
    result, truth = _result_sampled_from_truth(tmp_path, "knot")
    maps = SVBRDFMaps.load(result)
    means = texel_means(SVBRDFMaps.load(truth).diffuse_albedo, maps.shape).reshape(maps.diffuse_albedo.shape)
    dataclasses.replace(maps, diffuse_albedo=means).save(result)
    for r in material_errors(result, truth):
        assert r["rho_d_rmse_floor"] > 0.01 and r["rho_d_rmse"] == pytest.approx(r["rho_d_rmse_floor"], abs=1e-6), r
    assert all(
        r["rho_d_rmse_floor"] < 1e-6 for r in material_errors(*_result_from_truth(tmp_path / "same", name="knot"))
    )
    square = np.arange(16.0).reshape(4, 4, 1)  # 2 x 2 squares of a 4 x 4 map
    np.testing.assert_allclose(np.sort(texel_means(square, (2, 2))[:, 0]), [2.5, 4.5, 10.5, 12.5])


def test_material_errors_see_each_kind_of_error(tmp_path):
    half = np.zeros((32, 32))
    half[:, :16] = 1  # only the left half observed
    result, truth = _result_from_truth(tmp_path, observed=half)
    labels, _ = load_labels(truth)
    maps = SVBRDFMaps.load(result)
    maps.specular_albedo[labels == 0] = 0.5  # a lobe on matte
    maps.tangent = np.cross(maps.normal, maps.tangent)  # every tangent turned 90 deg
    maps.roughness = maps.roughness * np.e  # alphas e x too large
    maps.diffuse_albedo = maps.diffuse_albedo * 2
    maps.save(result)
    matte, _, metal, _ = material_errors(result, truth)
    assert matte["spurious_lobe"] == 1 and 0.4 < matte["coverage"] < 0.6
    assert matte["rho_d_ratio"] == pytest.approx(2, rel=0.05)
    assert metal["tangent_deg"] == pytest.approx(90, abs=1) and metal["log_alpha"] == pytest.approx(1, abs=0.05)


def test_coverage_counts_the_texels_photos_see_on_the_surface(tmp_path):
    """A texel off the atlas' charts is no texel of the object, and one no photo sees cannot be
    measured: neither counts against coverage. Photos from one side of the box see its top and
    that side; seen and coverage per material follow, against the texels' own normals and labels."""
    result, truth = _result_from_truth(tmp_path, name="box")
    mesh = load_mesh(result / "mesh.obj")
    shape = (32, 32)
    surface = surface_texels(mesh, shape)
    assert 0.3 < surface.mean() < 0.95  # xatlas leaves space between charts
    dev = load_scanner()
    centre = mesh.vertices.mean(0)
    poses = [look_at(centre + np.array([0.25, 0.05 * k, 0.2]), centre) for k in (-1, 0, 1)]
    seen = seen_texels(mesh, shape, dev, poses)
    assert not (seen & ~surface).any()
    tex = rasterize(mesh, shape)
    at = tex.row * shape[1] + tex.col
    to_cam = centre + np.array([0.25, 0.0, 0.2]) - tex.position
    facing = (tex.normal * to_cam).sum(1) > 0.3 * np.linalg.norm(to_cam, axis=1)  # clearly toward the photos
    away = (tex.normal * to_cam).sum(1) < -0.3 * np.linalg.norm(to_cam, axis=1)
    assert seen[at[facing]].all() and not seen[at[away]].any() and facing.any() and away.any()
    observed = seen.reshape(shape).astype(float)  # a trace for every seen texel: full coverage
    conf = np.ones((*shape, 3))
    conf[..., 1] = observed
    write_exr(result / "confidence.exr", conf)
    rows = material_errors(result, truth, dev, poses)
    labels = load_labels(truth)[0]
    assert all(r["coverage"] == 1 for r in rows if r["seen"] > 0)
    assert min(r["seen"] for r in rows) < 0.5 < max(r["seen"] for r in rows)
    assert labels.max() == len(rows) - 1
    conf[..., 1] = 0.0
    conf[:16, ..., 1] = observed[:16]  # the top half of the maps only
    write_exr(result / "confidence.exr", conf)
    half = material_errors(result, truth, dev, poses)
    assert all(h["seen"] == r["seen"] for h, r in zip(half, rows))
    assert any(0 < h["coverage"] < 1 for h in half)
    # without the photos every surface texel counts as seen
    assert all(r["seen"] == 1 for r in material_errors(result, truth))


def test_a_texel_hidden_by_the_mesh_is_not_seen():
    """Two stacked squares seen from above: the upper hides part of the lower; from below, nothing
    faces the camera."""
    from scans import flat_patch

    low = flat_patch(0.08, 8)
    high = flat_patch(0.03, 4)
    high.vertices[:, 2] = 0.02
    verts = np.concatenate([low.vertices, high.vertices])
    faces = np.concatenate([low.faces, high.faces + len(low.vertices)])
    uv = np.concatenate([low.uv * [0.5, 1.0], 0.6 + 0.3 * high.uv])  # two charts
    mesh = Mesh(verts, faces, uv, smooth_normals(verts, faces))
    shape = (48, 48)
    dev = load_scanner()
    cam = np.array([0.004, 0.002, 0.25])  # not straight down: look_at needs an up direction
    above = look_at(cam, np.zeros(3))
    seen = seen_texels(mesh, shape, dev, [above])
    tex = rasterize(mesh, shape)
    at = tex.row * shape[1] + tex.col
    # reference: the ray from a low texel to the camera centre meets the upper square's plane inside it
    is_low = tex.position[:, 2] < 0.01
    s = (0.02 - tex.position[:, 2]) / (cam[2] - tex.position[:, 2])
    cross = tex.position[:, :2] + s[:, None] * (cam[:2] - tex.position[:, :2])
    hidden = is_low & (np.abs(cross) < 0.015).all(1)
    margin = is_low & (np.abs(np.abs(cross) - 0.015) < 0.002).any(1)  # at the edge: either answer
    assert hidden.sum() > 20 and (~hidden & ~margin).sum() > 100
    assert not seen[at[hidden & ~margin]].any() and seen[at[~hidden & ~margin]].all()
    below = look_at(cam * [1, 1, -1], np.zeros(3))
    assert not seen_texels(mesh, shape, dev, [below]).any()


def test_material_errors_need_labels(tmp_path):
    result, truth = _result_from_truth(tmp_path)
    (truth / "labels.png").unlink()
    with pytest.raises(NtpInputError, match="labels.png"):
        material_errors(result, truth)


def test_the_relit_budget_finds_the_material_and_maps_that_lose_ssim(tmp_path):
    """A result that is the truth but for the print's diffuse albedo (halved) and the brushed
    metal's lobe (a quarter of its rho_s): each gains only where it was spoiled, and the whole truth
    makes the ceiling, which is perfect (the result has the truth's resolution)."""
    result, truth = _result_from_truth(tmp_path)
    labels, table = load_labels(truth)
    names = [m["name"] for m in table]
    maps = SVBRDFMaps.load(result)
    maps.diffuse_albedo[labels == names.index("matte_print")] *= 0.5
    maps.specular_albedo[labels == names.index("metal_brushed_dark")] *= 0.25
    maps.save(result)
    b = relit_budget(result, truth.parent / "mesh.obj", truth, lights=1, scale=0.1)
    rows = {r["material"]: r for r in b["materials"]}
    assert list(rows) == [*names, "all"]
    assert b["ceiling"] == pytest.approx(1.0) and b["relit_ssim"] < 0.99
    assert rows["all"]["everything"] == pytest.approx(b["ceiling"] - b["relit_ssim"])
    assert rows["matte_print"]["diffuse"] > 0.005 and rows["metal_brushed_dark"]["lobe"] > 0.005
    for name, spoiled in (("matte_print", "diffuse"), ("metal_brushed_dark", "lobe")):
        others = [rows[name][g] for g in ("diffuse", "normal", "lobe", "tangent") if g != spoiled]
        assert np.abs(others).max() < 1e-6, rows[name]  # the truth at the centres: the same maps
    for name in ("plastic_glossy", "lacquer_mirror"):
        assert np.abs([v for g, v in rows[name].items() if g != "material"]).max() < 1e-6, rows[name]


def test_the_relit_budget_swaps_tangents_without_opposing_the_results_signs(tmp_path):
    """A lobe's axis has no sign: a result whose tangents are all the truth's negated renders as the
    truth does, and swapping one material's true tangents into it gains nothing — the swapped axes
    take the result's sign, or that material's boundary would hold opposed neighbours."""
    result, truth = _result_from_truth(tmp_path)
    maps = SVBRDFMaps.load(result)
    maps.tangent *= -1.0
    maps.save(result)
    b = relit_budget(result, truth.parent / "mesh.obj", truth, lights=1, scale=0.1)
    assert b["relit_ssim"] == pytest.approx(1.0)
    for row in b["materials"]:
        assert abs(row["tangent"]) < 1e-6, row


def test_specular_error_is_over_texels_with_a_lobe():
    # texels pooled over materials (the refine bench's baseline): a matte one has no lobe to compare
    n = np.array([[0.0, 0.0, 1.0]] * 3)
    maps = {
        "normal": n,
        "tangent": np.array([[1.0, 0.0, 0.0]] * 3),
        "roughness": np.array([[0.1, 0.1]] * 3),
        "diffuse_albedo": np.full((3, 3), 0.5),
    }
    true = {**maps, "specular_albedo": np.array([[1.0] * 3, [2.0] * 3, [0.0] * 3])}
    rec = {**maps, "specular_albedo": np.array([[1.0] * 3, [2.0] * 3, [0.5] * 3])}
    with np.errstate(all="raise"):
        errors = parameter_errors(rec, true, matte=False)
    assert errors["log_rho_s"] == 0.0 and errors["log_alpha"] == 0.0 and errors["normal_deg"] == 0.0
    only_matte = {key: v[2:] for key, v in true.items()}
    assert np.isnan(parameter_errors({key: v[2:] for key, v in rec.items()}, only_matte, matte=False)["log_rho_s"])


def test_pose_error_modulo_a_symmetry_forgives_the_turn_the_mesh_cannot_show():
    from ntp_engine.scanner.camera import look_at
    from ntp_engine.sim.evaluate import pose_error, pose_error_modulo, turned_about

    centre = np.array([0.01, -0.02, 0.03])
    truth = {f"{k}": look_at(centre + [0.3 * np.cos(k), 0.3 * np.sin(k), 0.2], centre) for k in range(6)}
    turned = {n: m @ turned_about(centre, 180.0) for n, m in truth.items()}  # the half-turned placement
    assert pose_error(turned, truth)["rotation_median_deg"] > 90  # wrong, without the symmetry
    half = pose_error_modulo(turned, truth, centre, [180.0])
    assert half["rotation_median_deg"] < 1e-6 and half["centre_median_m"] < 1e-9 and half["symmetry_turn_deg"] == 180.0
    assert pose_error_modulo(turned, truth, centre, [])["rotation_median_deg"] > 90  # no symmetry: no forgiveness
    odd = {n: m @ turned_about(centre, 37.3) for n, m in truth.items()}  # a body of revolution: any turn
    every = pose_error_modulo(odd, truth, centre, None)
    assert every["rotation_median_deg"] < 0.02 and abs(every["symmetry_turn_deg"] - 37.3) < 0.02
