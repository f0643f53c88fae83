"""The object's outline against the marker board: the print seen where nothing hides it, placements
that poke into seen print costed, the whole-circle sweep finding the demo's placement from the
cameras' aim, a mesh that is not the object's refused."""

import json

import numpy as np
import pytest

from ntp_engine.io.mesh import Mesh, load_mesh
from ntp_engine.io.raycast import RayCaster
from ntp_engine.register.align import Alignment
from ntp_engine.register.board_poses import first_placement
from ntp_engine.register.check import confirmed_by_outline, outline_check, outline_fits
from ntp_engine.register.photo_stack import PhotoStack
from ntp_engine.register.refusal import refusal
from ntp_engine.register.silhouette import Silhouettes, board_hits, board_seen, penetration, turned
from ntp_engine.scanner import camera
from ntp_engine.scanner.scan_folder import load_scan, read_photo
from ntp_engine.sim.virtual_scan import ScanConfig, virtual_scan


@pytest.fixture(scope="module")
def board_scan(tmp_path_factory):
    """Sixteen photos of the demo standing on an A4 board (quarter size: 0.53 mm a pixel)."""
    out = tmp_path_factory.mktemp("outline") / "scan"
    virtual_scan(out, cfg=ScanConfig(views=16, scale=0.25, board="A4"))
    return out


@pytest.fixture(scope="module")
def scene(board_scan):
    """The scan, its photos, the board's true poses (camera from board) and the mesh's true
    placement on the board (board -> mesh frame)."""
    scan = load_scan(board_scan)
    capture = json.loads((board_scan / "ground_truth" / "capture.json").read_text())
    world_from_board = np.array(capture["board"]["world_from_board"])
    poses = json.loads((board_scan / "ground_truth" / "poses.json").read_text())
    names = [p.name for p in scan.photo_paths]
    camera_from_board = np.stack([np.array(poses[n]) @ world_from_board for n in names])
    photos = PhotoStack((read_photo(scan.photos_dir / n, scan.scanner) for n in names), scan.scanner)
    truth = Alignment(1.0, world_from_board[:3, :3], world_from_board[:3, 3], float("nan"), 0, 0, 0)
    return scan, photos, camera_from_board, truth, names


def _error_mm(a: Alignment, b: Alignment, points: np.ndarray) -> float:
    """The largest distance between the board positions two placements give the mesh's points."""
    pa, pb = (points - a.translation) @ a.rotation, (points - b.translation) @ b.rotation
    return 1e3 * float(np.linalg.norm(pa - pb, axis=1).max())


def test_the_print_is_seen_where_nothing_hides_it(scene):
    scan, photos, camera_from_board, truth, _ = scene
    mesh = load_mesh(scan.mesh_path)
    caster = RayCaster([mesh.triangles])
    rays = camera.pixel_rays(photos.scanner)
    taken, found = [], []
    for v in range(len(camera_from_board)):
        linear = photos.linear[v].permute(1, 2, 0).numpy()
        usable = photos.usable[v, 0].numpy() > 0
        seen, paper = board_seen(linear, usable, photos.scanner, camera_from_board[v], scan.board)
        pose = truth.camera_from_mesh(camera_from_board[v])  # camera from mesh (the world)
        origin = -pose[:3, :3].T @ pose[:3, 3]
        hits = caster.intersect(
            np.broadcast_to(origin, rays.shape).reshape(-1, 3), (rays @ pose[:3, :3]).reshape(-1, 3)
        )
        object_px = (hits.geom >= 0).reshape(seen.shape) & paper
        free = paper & ~object_px
        taken.append((seen & object_px).sum() / object_px.sum())
        found.append((seen & free).sum() / free.sum())
    # measured: of the object's pixels 0-1.5% taken for print (median 0.05%: the board mirrored in the
    # lacquer); of the free paper 90-99.9% seen (the misses: the object's shadow at grazing views)
    assert np.median(taken) < 0.005 and max(taken) < 0.03, taken
    assert min(found) > 0.85 and np.median(found) > 0.98, found


def test_board_hits_meet_the_plane_where_the_camera_projects_it(scene):
    _, photos, camera_from_board, _, _ = scene
    xy, ahead = board_hits(photos.scanner, camera_from_board[3])
    rows, cols = np.nonzero(ahead)
    pick = np.random.default_rng(0).choice(len(rows), 200, replace=False)
    points = np.concatenate([xy[rows[pick], cols[pick]], np.zeros((200, 1))], 1)
    cam = points @ camera_from_board[3][:3, :3].T + camera_from_board[3][:3, 3]
    import torch

    px = camera.project(photos.scanner, torch.as_tensor(cam)).numpy()
    assert np.abs(px - np.stack([cols[pick], rows[pick]], 1)).max() < 1e-6


def test_penetration_is_the_depth_into_seen_print():
    seen = np.zeros((21, 21), bool)
    seen[:, 10:] = True  # the print seen on the right half
    depth = penetration(seen)
    assert depth[5, 9] == 0 and depth[5, 10] == pytest.approx(1.0, abs=0.05)
    assert depth[5, 15] == pytest.approx(6.0, abs=0.1)


def test_a_turned_or_shifted_placement_pokes_into_the_print(scene):
    scan, photos, camera_from_board, truth, _ = scene
    mesh = load_mesh(scan.mesh_path)
    outline = Silhouettes(photos, camera_from_board, scan.board, mesh)
    at_truth = outline.costs(truth, fine=True).mean()
    for turn, shift in ((np.radians(20.0), np.zeros(2)), (0.0, np.array([3e-3, 0.0]))):
        moved = outline.costs(turned(truth, turn, shift, outline.pivot), fine=True).mean()
        # measured 0.03 px^2 at the truth (the outline's own blur), 0.57 turned 20 deg or shifted 3 mm
        assert moved > 4 * at_truth, (turn, shift, moved, at_truth)


def test_the_sweep_places_the_demo_from_the_cameras_aim_and_confirms_it(scene):
    scan, photos, camera_from_board, truth, names = scene
    mesh = load_mesh(scan.mesh_path)
    outline = Silhouettes(photos, camera_from_board, scan.board, mesh)
    found = outline.place(first_placement(mesh, list(camera_from_board)))
    # measured 0.17 mm (the surface's farthest point) at 0.53 mm a pixel, spread 0.24 px, the best
    # rival 4.4 standard errors worse
    assert _error_mm(found.alignment, truth, mesh.vertices) < 1.5
    check = outline_check(found, dict(zip(names, camera_from_board, strict=True)), names, mesh, photos.scanner.fx)
    assert outline_fits(check) and confirmed_by_outline(check), check.outline
    assert check.to_json()["outline"]["rivals"]  # the other azimuths it compared, each with its significance


def test_a_mesh_that_is_not_the_objects_does_not_fit_the_outline(scene):
    scan, photos, camera_from_board, _, names = scene
    mesh = load_mesh(scan.mesh_path)
    centre = 0.5 * (mesh.vertices.min(0) + mesh.vertices.max(0))
    # measured: 5% wider, 12.5% of its points over seen print at its best placement; 10% wider (here)
    # 18.6%; 25% wider 24%
    bigger = Mesh((mesh.vertices - centre) * [1.1, 1.1, 1.0] + centre, mesh.faces, mesh.uv, mesh.normals)
    outline = Silhouettes(photos, camera_from_board, scan.board, bigger)
    found = outline.place(first_placement(bigger, list(camera_from_board)))
    check = outline_check(found, dict(zip(names, camera_from_board, strict=True)), names, bigger, photos.scanner.fx)
    assert not outline_fits(check) and not confirmed_by_outline(check), check.outline
    why = refusal(check)
    assert why is not None and why.startswith("the object's outline against the board does not fix"), why


def test_a_noisy_symmetric_meshs_turn_is_equivalent_within_its_stated_accuracy():
    from ntp_engine.register.check import _SamePlacement
    from ntp_engine.sim.scanner_mesh import scanner_mesh
    from ntp_engine.sim.shapes import box_mesh
    from ntp_engine.sim.virtual_scan import surface_error

    truth = box_mesh(n=24)
    noisy = scanner_mesh(truth, seed=0, noise_m=3e-4)
    accuracy = surface_error(noisy, truth)
    centre = 0.5 * (noisy.vertices.min(0) + noisy.vertices.max(0))
    pixel = 5e-4  # the benches' quarter size: the photos alone see 0.25 px = 0.13 mm
    alone = _SamePlacement(noisy, centre, pixel, [0.0, 180.0, 90.0])
    stated = _SamePlacement(noisy, centre, pixel, [0.0, 180.0, 90.0], accuracy)
    # the half turn moves the noisy mesh ~0.85 sigma from itself: beyond what a photo sees, within
    # what two scans of one box would differ by (sqrt(2) sigma); a quarter turn of a 9 x 6.5 cm box
    # is no symmetry at any accuracy
    assert alone.same == [True, False, False] and stated.same == [True, True, False], (accuracy, alone.apart)
