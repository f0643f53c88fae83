import torch

from ntp_engine.physics.frame import (
    any_tangent,
    frame_from_normal_tangent,
    rotation_from_vector,
    safe_normalize,
    to_local,
    to_world,
    turned_about_normal,
)

F64 = torch.float64


def test_frame_is_orthonormal_right_handed_and_inverts():
    gen = torch.Generator().manual_seed(0)
    n = torch.randn(1000, 3, generator=gen, dtype=F64)
    t = torch.randn(1000, 3, generator=gen, dtype=F64)
    fr = frame_from_normal_tangent(n, t)
    eye = torch.eye(3, dtype=F64).expand(1000, 3, 3)
    torch.testing.assert_close(fr @ fr.transpose(-1, -2), eye)
    torch.testing.assert_close(torch.linalg.det(fr), torch.ones(1000, dtype=F64))
    torch.testing.assert_close(fr[:, 2], torch.nn.functional.normalize(n, dim=-1))
    v = torch.randn(1000, 3, generator=gen, dtype=F64)
    torch.testing.assert_close(to_world(to_local(v, fr), fr), v)
    # local z of the normal itself is 1, of the tangent direction x is positive
    torch.testing.assert_close(to_local(fr[:, 2], fr), torch.tensor([0, 0, 1.0], dtype=F64).expand(1000, 3))
    assert (to_local(t, fr)[:, 0] > 0).all()


def test_degenerate_tangent_falls_back():
    n = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]], dtype=F64)
    fr = frame_from_normal_tangent(n, n.clone())  # tangent parallel to the normal
    assert torch.isfinite(fr).all()
    torch.testing.assert_close(fr @ fr.transpose(-1, -2), torch.eye(3, dtype=F64).expand(3, 3, 3))
    fr0 = frame_from_normal_tangent(n, torch.zeros_like(n))
    assert torch.isfinite(fr0).all()


def test_any_tangent_orthogonal_everywhere():
    n = torch.nn.functional.normalize(torch.randn(5000, 3, dtype=F64), dim=-1)
    n = torch.cat([n, torch.tensor([[0, 0, 1.0], [0, 0, -1.0], [0, 1.0, 0], [1e-9, 0, -1]], dtype=F64)])
    n = torch.nn.functional.normalize(n, dim=-1)
    t = any_tangent(n)
    torch.testing.assert_close(t.norm(dim=-1), torch.ones(len(n), dtype=F64))
    assert (t * n).sum(-1).abs().max() < 1e-12


def test_safe_normalize_zero_has_finite_gradient():
    v = torch.zeros(2, 3, requires_grad=True)
    out = safe_normalize(v)
    out.sum().backward()
    assert torch.equal(out, torch.tensor([[0, 0, 1.0], [0, 0, 1.0]]))
    assert torch.isfinite(v.grad).all()


def test_rotation_from_vector():
    r = torch.randn(1000, 3, dtype=torch.float64) * torch.logspace(-9, 0.5, 1000, dtype=torch.float64)[:, None]
    R = rotation_from_vector(r)
    eye = torch.eye(3, dtype=torch.float64).expand_as(R)
    torch.testing.assert_close(R.transpose(-1, -2) @ R, eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(1000, dtype=torch.float64))
    torch.testing.assert_close((R @ r[..., None])[..., 0], r)  # the axis stays put
    quarter = rotation_from_vector(torch.tensor([0.0, 0.0, torch.pi / 2], dtype=torch.float64))
    torch.testing.assert_close(
        quarter @ torch.tensor([1.0, 0, 0], dtype=torch.float64), torch.tensor([0.0, 1, 0], dtype=torch.float64)
    )  # right-handed
    z = torch.zeros(3, requires_grad=True)
    rotation_from_vector(z).sum().backward()
    assert torch.isfinite(z.grad).all()


def test_turned_about_normal_is_a_rotation_about_n():
    gen = torch.Generator().manual_seed(3)
    fr = frame_from_normal_tangent(
        torch.randn(50, 3, generator=gen, dtype=F64), torch.randn(50, 3, generator=gen, dtype=F64)
    )
    angle = torch.rand(50, generator=gen, dtype=F64) * 6.0
    out = turned_about_normal(fr, angle)
    torch.testing.assert_close(out, fr @ rotation_from_vector(fr[:, 2] * angle[:, None]).transpose(-1, -2))
    torch.testing.assert_close(out[:, 2], fr[:, 2])
    torch.testing.assert_close(torch.linalg.det(out), torch.ones(50, dtype=F64))
    torch.testing.assert_close((out[:, 0] * fr[:, 0]).sum(-1), angle.cos())
    torch.testing.assert_close(turned_about_normal(fr, torch.full((50,), torch.pi / 2, dtype=F64))[:, 0], fr[:, 1])
