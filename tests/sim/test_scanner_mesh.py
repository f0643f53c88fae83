"""The mesh a shape scanner delivers: smoothed, noisy by the asked amount, seams closed, UVs kept."""

import numpy as np

from ntp_engine.io.mesh import Mesh, smooth_normals
from ntp_engine.sim.generated import generated_object
from ntp_engine.sim.scanner_mesh import scanner_mesh, taubin
from ntp_engine.sim.shapes import vase_mesh


def test_taubin_removes_ripples_and_keeps_the_shape():
    vase = vase_mesh(64, 32)
    weld = np.unique(np.round(vase.vertices, 9), axis=0, return_inverse=True)[1].reshape(-1)
    ripple = 2e-4 * np.random.default_rng(0).standard_normal((weld.max() + 1, 3))[weld]  # seams stay welded
    rim = vase.vertices[:, 2] == 0
    ripple[rim] = 0.0
    smoothed = taubin(Mesh(vase.vertices + ripple, vase.faces, vase.uv, vase.normals), 4)
    clean = taubin(vase, 4)
    left = np.linalg.norm(smoothed - clean, axis=1).mean()  # what remains of the ripple
    assert left < 0.5 * np.linalg.norm(ripple, axis=1).mean()
    assert np.abs(clean - vase.vertices).max() < 2e-3  # the shape stays (no shrinking)
    np.testing.assert_allclose(smoothed[rim], vase.vertices[rim], atol=1e-12)  # the base stands where it stood


def test_the_noise_is_the_asked_amount_along_the_normals_and_seams_stay_closed():
    vase = vase_mesh(64, 32)
    quiet = scanner_mesh(vase, seed=3, noise_m=0.0)
    noisy = scanner_mesh(vase, seed=3, noise_m=4e-4)
    d = noisy.vertices - quiet.vertices
    along = (d * smooth_normals(quiet.vertices, quiet.faces)).sum(1)
    assert 3e-4 < along.std() < 5e-4 and np.abs(d - along[:, None] * quiet.normals).max() < 1e-4
    seam = np.isclose(vase.uv[:, 0], 0.0) | np.isclose(vase.uv[:, 0], 1.0)  # the u = 0 / u = 1 duplicates
    key = np.unique(np.round(vase.vertices[seam], 9), axis=0, return_inverse=True)[1].reshape(-1)
    for k in np.unique(key):
        assert np.ptp(noisy.vertices[seam][key == k], axis=0).max() < 1e-12
    np.testing.assert_array_equal(noisy.uv, vase.uv)
    np.testing.assert_array_equal(scanner_mesh(vase, seed=3, noise_m=4e-4).vertices, noisy.vertices)  # seeded
    assert not np.array_equal(scanner_mesh(vase, seed=4, noise_m=4e-4).vertices, noisy.vertices)


def test_a_generated_objects_scanner_mesh_is_its_surface_triangulated_coarser():
    obj = generated_object("star-1001")
    scan = obj.scanner_mesh()
    assert len(scan.faces) < 0.5 * len(obj.mesh.faces) and scan.uv is not None
    lo, hi = obj.mesh.vertices.min(0), obj.mesh.vertices.max(0)
    assert np.abs(scan.vertices.min(0) - lo).max() < 3e-3 and np.abs(scan.vertices.max(0) - hi).max() < 3e-3
