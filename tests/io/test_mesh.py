import numpy as np
import pytest

from ntp_engine.io.errors import NtpInputError
from ntp_engine.io.mesh import Mesh, load_mesh, save_obj, smooth_normals


def _square(uv=True):
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    return Mesh(v, f, v[:, :2].copy() if uv else None, smooth_normals(v, f))


def test_obj_round_trip_keeps_positions_uvs_and_area(tmp_path):
    m = _square()
    save_obj(tmp_path / "m.obj", m)
    back = load_mesh(tmp_path / "m.obj")
    np.testing.assert_allclose(back.vertices, m.vertices)
    np.testing.assert_allclose(back.uv, m.uv)
    assert back.area() == pytest.approx(1.0) and np.allclose(back.face_normals(), [0, 0, 1])


def test_smooth_normals_ignore_uv_seams():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0.0], [1, 1, 0.5]])  # vertex 3 duplicates 1 (a seam)
    f = np.array([[0, 1, 2], [3, 4, 2]])
    n = smooth_normals(v, f)
    np.testing.assert_allclose(n[1], n[3])


def test_bad_meshes_name_the_file(tmp_path):
    with pytest.raises(NtpInputError, match="missing.obj: mesh file not found"):
        load_mesh(tmp_path / "missing.obj")
    (tmp_path / "empty.obj").write_text("v 0 0 0\n")
    with pytest.raises(NtpInputError, match="empty.obj"):
        load_mesh(tmp_path / "empty.obj")
