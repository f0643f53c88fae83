import math

import pytest
import torch

from ntp_engine.physics.brdf import ggx
from ntp_engine.physics.frame import reflect
from ntp_engine.physics.lumitexel import (
    CUBE_SIDE,
    diffuse_lumitexel,
    render_lumitexels,
    specular_lumitexel,
    texel_positions,
    unfold_cross,
)

F64 = torch.float64
Z = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
X = torch.tensor([1.0, 0.0, 0.0], dtype=F64)


def test_layout_documented_order():
    p = texel_positions(8, F64)
    h = CUBE_SIDE / 2
    assert p.shape == (384, 3)
    assert torch.allclose(p.abs().amax(-1), torch.full((384,), h, dtype=F64))
    for face, (axis, sign) in enumerate([(0, 1), (0, -1), (1, 1), (1, -1), (2, 1), (2, -1)]):
        assert torch.allclose(p[face * 64 : (face + 1) * 64, axis], torch.full((64,), sign * h, dtype=F64))
    # +x face, row 0, col 0: sc = -z, tc = -y -> (h, +, +) per OpenGL
    u = -1 + 1 / 8
    torch.testing.assert_close(p[0], torch.tensor([h, -u * h, -u * h], dtype=F64))
    # +z face, row 0, col 1: x grows with the column, y decreases with the row (tc = -y)
    assert p[4 * 64 + 1, 0] > p[4 * 64, 0] and p[4 * 64 + 8, 1] < p[4 * 64, 1]
    assert texel_positions(32).shape == (6144, 3)


def test_diffuse_lumitexel_is_lambert_inverse_square():
    p = texel_positions(8, F64)
    m = diffuse_lumitexel(Z, torch.tensor([0.5], dtype=F64))
    r2 = (p * p).sum(-1)
    cos = (p[:, 2] / r2.sqrt()).clamp_min(0)
    torch.testing.assert_close(m[:, 0], 0.5 / math.pi * cos / r2)
    assert (m[64 * 5 :] == 0).all() and (m[64 * 4 : 64 * 5] > 0).all()  # the -z face is below the horizon


def test_specular_matches_brdf_and_peaks_at_mirror_direction():
    n = torch.nn.functional.normalize(torch.tensor([0.3, -0.2, 1.0], dtype=F64), dim=0)
    ax, ay = torch.tensor(0.02, dtype=F64), torch.tensor(0.02, dtype=F64)
    m = specular_lumitexel(n, X, torch.ones(1, dtype=F64), ax, ay)[:, 0]
    p = texel_positions(32, F64)
    wi = p / p.norm(dim=-1, keepdim=True)
    peak_dir = reflect(Z, n)
    assert torch.dot(wi[m.argmax()], peak_dir) > math.cos(math.radians(4))
    # one texel against a direct evaluation in the shading frame
    k = int(m.argmax())
    t = torch.nn.functional.normalize(X - n * torch.dot(X, n), dim=0)
    b = torch.linalg.cross(n, t, dim=0)
    fr = torch.stack([t, b, n])
    f = ggx(fr @ wi[k], fr @ Z, torch.zeros(1, dtype=F64), torch.ones(1, dtype=F64), ax, ay)
    assert float(m[k]) == pytest.approx(float(f[0] * torch.dot(wi[k], n) / (p[k] @ p[k])), rel=1e-10)


def test_symmetries_of_the_anisotropic_lobe():
    n = torch.nn.functional.normalize(torch.tensor([0.1, 0.2, 1.0], dtype=F64), dim=0)
    t = torch.nn.functional.normalize(torch.linalg.cross(n, torch.tensor([0.0, 1.0, 0.0], dtype=F64), dim=0), dim=0)
    b = torch.linalg.cross(n, t, dim=0)
    one = torch.ones(1, dtype=F64)
    ax, ay = torch.tensor(0.3, dtype=F64), torch.tensor(0.05, dtype=F64)
    m = specular_lumitexel(n, t, one, ax, ay)
    torch.testing.assert_close(specular_lumitexel(n, -t, one, ax, ay), m)
    torch.testing.assert_close(specular_lumitexel(n, b, one, ay, ax), m)
    assert not torch.allclose(specular_lumitexel(n, b, one, ax, ay), m)


def test_batched_shapes_and_channels():
    n = torch.tensor([[0.0, 0.0, 1.0]] * 4)
    t = torch.tensor([[1.0, 0.0, 0.0]] * 4)
    d, s = render_lumitexels(
        n.view(2, 2, 3),
        t.view(2, 2, 3),
        torch.rand(2, 2, 3),
        torch.rand(2, 2, 3),
        torch.full((2, 2), 0.1),
        torch.full((2, 2), 0.2),
    )
    assert d.shape == (2, 2, 384, 3) and s.shape == (2, 2, 6144, 3) and d.dtype == torch.float32
    img = unfold_cross(s, 32)
    assert img.shape == (2, 2, 96, 128, 3)
    assert torch.equal(img[..., 32:64, 32:64, :], s[..., 4 * 1024 : 5 * 1024, :].reshape(2, 2, 32, 32, 3))
    with pytest.raises(ValueError):
        unfold_cross(s, 8)


def test_float32_extremes_are_finite_with_finite_gradients():
    p = texel_positions(32)
    aim = p[4 * 1024 + 100] / p[4 * 1024 + 100].norm()  # a light exactly at the mirror direction
    n = torch.nn.functional.normalize(aim + torch.tensor([0.0, 0.0, 1.0]), dim=0)
    n = torch.stack([n, torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 0.0, -1.0])]).requires_grad_()
    t = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    a = torch.tensor([0.006, 0.5, 0.006], requires_grad=True)
    d, s = render_lumitexels(n, t, torch.ones(3, 1), torch.full((3, 1), 10.0), a, a)
    assert torch.isfinite(s).all() and torch.isfinite(d).all() and float(s.detach().max()) > 1e3
    (s.sum() + d.sum()).backward()
    assert torch.isfinite(n.grad).all() and torch.isfinite(a.grad).all()
