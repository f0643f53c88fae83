"""The photos a registration is judged on and the nuisances eliminated from them: each point's albedo
and each photo's smooth shading field, nothing else."""

import torch

from ntp_engine.register.photo_stack import eliminate_nuisances


def test_eliminate_nuisances_removes_albedos_and_photo_fields_and_nothing_else():
    g = torch.Generator().manual_seed(0)
    V, N = 6, 300
    field = torch.cat([torch.ones(N, 1), torch.rand(N, 3, generator=g) - 0.5], 1)
    w = torch.rand(V, N, 3, generator=g) * (torch.rand(V, N, 1, generator=g) < 0.6)  # some unobserved
    albedo, fields = torch.randn(N, 3, generator=g), torch.randn(V, 4, 3, generator=g)
    nuisance = (albedo[None] + torch.einsum("nk,vkc->vnc", field, fields))[..., None]
    signal = torch.randn(V, N, 3, 1, generator=g)
    seen = w[..., None] > 0
    # a pure nuisance leaves nothing; with albedos alone eliminated the fields would remain
    assert eliminate_nuisances(field, w, nuisance)[seen].abs().max() < 1e-4
    assert eliminate_nuisances(field[:, :0], w, nuisance)[seen].abs().max() > 0.5
    # a projection: the residual is weighted-orthogonal to every nuisance, and adding one changes nothing
    out = eliminate_nuisances(field, w, signal)
    assert (w[..., None] * out).sum(0).abs().max() < 1e-4  # each point's albedo
    assert torch.einsum("vnc,nk,vncd->vkcd", w, field, out).abs().max() < 1e-3  # each photo's field
    assert torch.allclose(eliminate_nuisances(field, w, signal + nuisance)[seen], out[seen], atol=1e-4)
    assert torch.allclose(eliminate_nuisances(field, w, out)[seen], out[seen], atol=1e-4)
    # columns are fitted alike, one by one or together (where observed: elsewhere the residual is
    # not meaningful — the ridge's pick of the common field, 1e-2 apart between the two solves on
    # some CPUs' float32)
    both = eliminate_nuisances(field, w, torch.cat([signal, 2 * signal], -1))
    assert torch.allclose(both[..., 1:][seen], 2 * out[seen], atol=1e-4)
    # an unobserved value does not enter, even an infinite one (0 * inf would poison every point)
    poisoned = torch.where(seen, signal, torch.tensor(float("inf")))
    assert torch.allclose(eliminate_nuisances(field, w, poisoned)[seen], out[seen], atol=1e-4)
    poisoned = torch.where(seen, torch.cat([signal, 2 * signal], -1), torch.tensor([float("nan"), -float("inf")]))
    assert torch.allclose(
        eliminate_nuisances(field, w, poisoned)[seen.expand(-1, -1, -1, 2)], both[seen.expand_as(both)], atol=1e-4
    )


def test_eliminate_nuisances_with_many_photos_after_threads_are_set():
    # 48 photos x 4 field terms: a 192 x 192 system per channel, which torch's batched LU solve
    # failed on (bogus pivots) once torch.set_num_threads had been called, as --threads does
    g = torch.Generator().manual_seed(2)
    V, N = 48, 400
    field = torch.cat([torch.ones(N, 1), torch.rand(N, 3, generator=g) - 0.5], 1)
    w = torch.rand(V, N, 3, generator=g)
    x = torch.randn(V, N, 3, 1, generator=g)
    threads = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        out = eliminate_nuisances(field, w, x)
    finally:
        torch.set_num_threads(threads)
    assert torch.isfinite(out).all()
    assert torch.einsum("vnc,nk,vncd->vkcd", w, field, out).abs().max() < 1e-3  # each photo's field removed
