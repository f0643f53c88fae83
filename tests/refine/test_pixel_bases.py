"""The compiled pixel bases equal their torch definitions (float64 references): the diffuse basis
the horizon-clipped sum over the emitters, the specular one the torch lobe summed, its derivatives
automatic differentiation of that, the per-emitter lobe weights the torch lobe, and their
per-sample inputs the emitter geometry."""

import dataclasses
import math

import numpy as np
import pytest
import torch

from ntp_engine.physics.brdf import fresnel_schlick
from ntp_engine.physics.frame import frame_from_normal_tangent, rotation_from_vector, safe_normalize, to_local
from ntp_engine.physics.measurement import local_emitter_geometry
from ntp_engine.refine.pixel_bases import (
    diffuse_basis,
    diffuse_basis_and_margin,
    diffuse_basis_near,
    emitter_directions,
    lobe_weights,
    pack_emitters,
    selected_emitters,
    specular_basis,
    specular_basis_and_derivatives,
)
from ntp_engine.scanner.device_file import load_scanner


def _lobe(frame: torch.Tensor, wi, wo, falloff, alpha) -> torch.Tensor:
    """The torch definition the compiled loops are checked against: Eq. 1's specular weight per
    emitter, F D G / (4 cos_i cos_o) (wi.n)+ * falloff, ``(N, V, K)``, for shading frames ``frame
    (N, 3, 3)`` (rows t, b, n in the geometric frame), geometric-frame ``wi (N, V, K, 3)``, ``wo
    (N, V, 3)`` and ``alpha (N, 2)`` — the cancelled Smith form of ``physics.brdf.ggx_specular``
    with Schlick's F on wi.h."""
    h = safe_normalize(wi + wo[:, :, None])
    fresnel_falloff = fresnel_schlick((wi * h).sum(-1)) * falloff
    f4 = frame[:, None, None]
    wi_s, h_s, wo_s = to_local(wi, f4), to_local(h, f4), to_local(wo, frame[:, None])
    ax, ay = alpha[:, 0, None, None], alpha[:, 1, None, None]
    q = (h_s[..., 0] / ax) ** 2 + (h_s[..., 1] / ay) ** 2 + h_s[..., 2] ** 2
    cos_i = wi_s[..., 2].clamp_min(0.0)
    lam_i = torch.sqrt(((ax * wi_s[..., 0]) ** 2 + (ay * wi_s[..., 1]) ** 2 + wi_s[..., 2] ** 2).clamp_min(1e-20))
    axo, ayo = ax[..., 0], ay[..., 0]
    lam_o = torch.sqrt(((axo * wo_s[..., 0]) ** 2 + (ayo * wo_s[..., 1]) ** 2 + wo_s[..., 2] ** 2).clamp_min(1e-20))
    seen = (wo_s[..., 2] > 0).to(wo_s.dtype) / (wo_s[..., 2].clamp_min(0.0) + lam_o)  # 0 below
    return cos_i * fresnel_falloff * seen[..., None] / (math.pi * ax * ay * q * q * (cos_i + lam_i))


def _soa(wi: torch.Tensor) -> torch.Tensor:
    """Directions ``(..., M, 3)`` as the compiled loops read them, ``(..., 3, M)``."""
    return wi.transpose(-1, -2).contiguous()


def _case(seed: int, N=6, V=5, M=40):
    g = torch.Generator().manual_seed(seed)
    d = torch.float64
    n = safe_normalize(torch.tensor([0.0, 0.0, 1.0], dtype=d) + 0.3 * torch.randn(N, 3, generator=g, dtype=d))
    frame = frame_from_normal_tangent(n, torch.randn(N, 3, generator=g, dtype=d))
    wi = safe_normalize(torch.randn(N, V, M, 3, generator=g, dtype=d) + torch.tensor([0, 0, 1.2], dtype=d))
    wo = safe_normalize(torch.randn(N, V, 3, generator=g, dtype=d) + torch.tensor([0, 0, 1.5], dtype=d))
    ff = torch.rand(N, V, M, generator=g, dtype=d)
    ff[:, :, -3:] = 0.0  # padding emitters: no light
    drive = torch.rand(N, V, M, 3, generator=g, dtype=d)
    alpha = torch.exp(torch.empty(N, 2, dtype=d).uniform_(math.log(0.02), math.log(0.5), generator=g))
    return frame, wi, wo, ff, drive, alpha


def _reference(frame, wi, wo, ff, drive, alpha, x):
    """The torch lobe summed over emitters, at shading-frame rotation x[:, :3] and log-alpha offsets x[:, 3:]."""
    f = rotation_from_vector(x[:, :3]).transpose(-1, -2) @ frame
    lobe = _lobe(f, wi, wo, ff, alpha * x[:, 3:].exp())
    return torch.einsum("nvm,nvmc->nvc", lobe, drive)


def test_packed_emitters_are_rows_of_vectors_over_the_emitters():
    _, wi, _, ff, drive, _ = _case(7)
    packed = pack_emitters(_soa(wi), ff, drive)
    assert packed.shape == (*ff.shape[:2], 6, ff.shape[2]) and packed.is_contiguous()
    assert torch.equal(packed[:, :, :3], wi.transpose(-1, -2))
    assert torch.equal(packed[:, :, 3:], ff[:, :, None] * drive.transpose(-1, -2))
    one = pack_emitters(_soa(wi), ff, drive[0, 0])  # one drive for every entry
    assert torch.equal(one[:, :, 3:], ff[:, :, None] * drive[0, 0].T)


@pytest.mark.slow  # measured over 5 s on 2 cores
@pytest.mark.parametrize("seed", [0, 1])
def test_bases_and_derivatives_match_the_torch_lobe(seed):
    frame, wi, wo, ff, drive, alpha = _case(seed)
    packed = pack_emitters(_soa(wi), ff, drive)
    spec, ds = specular_basis_and_derivatives(frame, packed, wo, alpha)
    x0 = torch.zeros(len(frame), 5, dtype=torch.float64)
    ref = _reference(frame, wi, wo, ff, drive, alpha, x0)
    assert ref.abs().max() > 0
    assert spec.dtype == ds.dtype == torch.float64  # the scipy baseline differentiates them numerically
    torch.testing.assert_close(spec, ref, rtol=1e-9, atol=1e-12 * float(ref.abs().max()))
    assert torch.equal(specular_basis(frame, packed, wo, alpha), spec)
    spec32, ds32 = specular_basis_and_derivatives(*(x.float() for x in (frame, packed, wo, alpha)))
    assert spec32.dtype == ds32.dtype == torch.float32
    torch.testing.assert_close(spec32.double(), ref, rtol=1e-4, atol=1e-6 * float(ref.abs().max()))
    # forward-mode derivatives by each of the 5 parameters
    for k in range(5):
        e = torch.zeros_like(x0)
        e[:, k] = 1.0
        _, jvp = torch.func.jvp(lambda x: _reference(frame, wi, wo, ff, drive, alpha, x), (x0,), (e,))
        scale = float(jvp.abs().max())
        torch.testing.assert_close(ds[:, :, k], jvp, rtol=1e-8, atol=1e-11 * scale)
        torch.testing.assert_close(ds32[:, :, k].double(), jvp, rtol=1e-3, atol=1e-5 * scale)


def test_a_widened_lobe_is_the_lobe_each_entry_sees_derived_by_the_surfaces_alphas():
    """With ``widening (N, V, 2)``, entry v sees alphas sqrt(alpha^2 + widening[:, v]) (``fit.
    footprint``); the derivatives stay those by the surface's own log alphas."""
    frame, wi, wo, ff, drive, alpha = _case(4)
    packed = pack_emitters(_soa(wi), ff, drive)
    g = torch.Generator().manual_seed(9)
    wide = 0.01 * torch.rand(*wo.shape[:2], 2, generator=g, dtype=torch.float64)

    def reference(x):
        f = rotation_from_vector(x[:, :3]).transpose(-1, -2) @ frame
        a = alpha * x[:, 3:].exp()
        out = []
        for v in range(wo.shape[1]):
            seen = torch.sqrt(a**2 + wide[:, v])
            sl = slice(v, v + 1)
            lobe = _lobe(f, wi[:, sl], wo[:, sl], ff[:, sl], seen)
            out.append(torch.einsum("nvm,nvmc->nvc", lobe, drive[:, sl]))
        return torch.cat(out, 1)

    x0 = torch.zeros(len(frame), 5, dtype=torch.float64)
    spec, ds = specular_basis_and_derivatives(frame, packed, wo, alpha, None, wide)
    ref = reference(x0)
    torch.testing.assert_close(spec, ref, rtol=1e-9, atol=1e-12 * float(ref.abs().max()))
    assert not torch.allclose(spec, specular_basis(frame, packed, wo, alpha))
    assert torch.equal(specular_basis(frame, packed, wo, alpha, None, wide), spec)
    for k in range(5):
        e = torch.zeros_like(x0)
        e[:, k] = 1.0
        _, jvp = torch.func.jvp(reference, (x0,), (e,))
        torch.testing.assert_close(ds[:, :, k], jvp, rtol=1e-8, atol=1e-11 * float(jvp.abs().max()))


def test_lobe_weights_are_the_torch_lobe_per_emitter():
    frame, wi, wo, ff, _, alpha = _case(3)
    wo[0, 1] = wo[0, 1] * torch.tensor([1.0, 1.0, -1.0], dtype=wo.dtype)  # seen from below: no lobe
    ref = _lobe(frame, wi, wo, ff, alpha)
    got = lobe_weights(frame, _soa(wi), wo, ff, alpha)
    assert got.dtype == torch.float64 and (ref > 0).any() and (ref == 0).any()
    torch.testing.assert_close(got, ref, rtol=1e-10, atol=1e-14 * float(ref.max()))
    assert torch.equal(got == 0, ref == 0)  # the same emitters score nothing: blocks rank the same
    got32 = lobe_weights(*(x.float() for x in (frame, _soa(wi), wo, ff, alpha)))
    assert got32.dtype == torch.float32
    torch.testing.assert_close(got32.double(), ref, rtol=1e-4, atol=1e-6 * float(ref.max()))


def test_rows_read_a_subset_without_copying_it():
    frame, wi, wo, ff, drive, alpha = _case(5)
    packed = pack_emitters(_soa(wi), ff, drive)
    rows = torch.tensor([4, 1, 1, 3])  # any order, repeats allowed
    spec, ds = specular_basis_and_derivatives(frame[rows], packed, wo, alpha[rows], rows)
    want, want_ds = specular_basis_and_derivatives(frame[rows], packed[rows], wo[rows], alpha[rows])
    assert torch.equal(spec, want) and torch.equal(ds, want_ds) and want.abs().max() > 0
    assert torch.equal(specular_basis(frame[rows], packed, wo, alpha[rows], rows), want)
    # the diffuse basis (and its horizon margins), the block ranking and the emitter selection too
    n, drive_k = frame[rows, 2], drive[0, 0]
    got, margin = diffuse_basis_and_margin(n, _soa(wi), ff, drive_k, rows)
    want, want_margin = diffuse_basis_and_margin(n, _soa(wi[rows]), ff[rows], drive_k)
    assert torch.equal(got, want) and torch.equal(margin, want_margin) and want.abs().max() > 0
    tilted = safe_normalize(n + 0.2)
    assert torch.equal(
        diffuse_basis_near(tilted, _soa(wi), ff, drive_k, got, n, margin, rows),
        diffuse_basis(tilted, _soa(wi[rows]), ff[rows], drive_k),
    )
    want = lobe_weights(frame[rows], _soa(wi[rows]), wo[rows], ff[rows], alpha[rows])
    assert torch.equal(lobe_weights(frame[rows], _soa(wi), wo, ff, alpha[rows], rows), want)
    top = want[..., :8].topk(2, -1).indices  # 8 blocks of 5 samples
    members = torch.arange(40).view(8, 5)
    w = _soa(wi)
    fine, coarse = (w, ff, drive[0, 0, :40]), (_soa(wi[:, :, :8]), ff[:, :, :8], drive[0, 0, :8])
    got = selected_emitters(top, members, fine, coarse, rows)
    picked = (w[rows], ff[rows], drive[0, 0, :40])
    want = selected_emitters(top, members, picked, (_soa(wi[rows, :, :8]), ff[rows, :, :8], drive[0, 0, :8]))
    assert torch.equal(got, want)


def test_selected_emitters_are_the_expanded_blocks_then_the_others_coarse():
    g = torch.Generator().manual_seed(6)
    N, V, K, C, S, B = 3, 4, 20, 5, 4, 2
    members = torch.randperm(K, generator=g)[: C * S].view(C, S)
    members[-1, -1] = K - 1  # a padding-like index: any sample
    fine = (torch.randn(N, V, K, 3, generator=g), torch.rand(N, V, K, generator=g), torch.rand(K, 3, generator=g))
    coarse = (torch.randn(N, V, C, 3, generator=g), torch.rand(N, V, C, generator=g), torch.rand(C, 3, generator=g))
    order = torch.stack([torch.randperm(C, generator=g) for _ in range(N * V)]).view(N, V, C)
    packed = selected_emitters(order[..., :B], members, (_soa(fine[0]), *fine[1:]), (_soa(coarse[0]), *coarse[1:]))
    assert packed.shape == (N, V, 6, B * S + C - B)
    for n in range(N):
        for v in range(V):
            k = members[order[n, v, :B]].flatten()
            c = order[n, v, B:].sort().values  # the other blocks in block order
            wi = torch.cat([fine[0][n, v, k], coarse[0][n, v, c]])
            ff = torch.cat([fine[1][n, v, k], coarse[1][n, v, c]])
            drive = torch.cat([fine[2][k], coarse[2][c]])
            assert torch.equal(packed[n, v], pack_emitters(_soa(wi[None, None]), ff[None, None], drive)[0, 0])


def test_no_light_and_views_from_below_give_zero():
    frame, wi, wo, ff, drive, alpha = _case(2)
    spec, ds = specular_basis_and_derivatives(frame, pack_emitters(_soa(wi), torch.zeros_like(ff), drive), wo, alpha)
    assert not spec.any() and not ds.any()
    frame, wi, wo, ff, drive, alpha = _case(3)
    below = -wo  # every view under the shading frame's horizon... for frames near +z
    below[..., 2] = -below[..., 2].abs() - 0.5
    packed = pack_emitters(_soa(wi), ff, drive)
    spec, ds = specular_basis_and_derivatives(frame, packed, safe_normalize(below), alpha)
    assert not spec.any() and not ds.any() and torch.isfinite(ds).all()


def test_emitters_below_the_horizon_or_opposite_the_view_add_nothing_and_stay_finite():
    """The loop has no branch per emitter: one below the shading horizon, or exactly opposite the
    view (a zero half vector), is multiplied by 0 — and must not turn the sums into NaN."""
    frame, wi, wo, ff, drive, alpha = _case(8)
    below = wi.clone()
    below[:, :, :10] = -wi[:, :, :10].abs() * torch.tensor([1.0, 1.0, 1.0], dtype=wi.dtype)
    below[:, :, 10] = -wo  # wi = -wo: h = 0
    below[:, :, :10, 2] = -below[:, :, :10, 2].abs() - 0.5
    below = safe_normalize(below)
    spec, ds = specular_basis_and_derivatives(frame, pack_emitters(_soa(below), ff, drive), wo, alpha)
    x0 = torch.zeros(len(frame), 5, dtype=torch.float64)
    ref = _reference(frame, below, wo, ff, drive, alpha, x0)
    assert torch.isfinite(spec).all() and torch.isfinite(ds).all() and ref.abs().max() > 0
    torch.testing.assert_close(spec, ref, rtol=1e-9, atol=1e-12 * float(ref.abs().max()))


def test_diffuse_basis_sums_the_emitters_above_the_horizon():
    frame, wi, _, ff, drive, _ = _case(4)
    normal, falloff, drive_k = frame[:, 2], ff, drive[0, 0]  # one drive per emitter for every entry
    above = ((wi * normal[:, None, None]).sum(-1) > 0).double() * falloff
    ref = torch.einsum("nvk,kc,nvkj->nvcj", above, drive_k, wi) / math.pi
    out = diffuse_basis(normal, _soa(wi), falloff, drive_k)
    assert out.shape == ref.shape and (above == 0).any() and ref.abs().max() > 0
    torch.testing.assert_close(out, ref, rtol=1e-9, atol=1e-12 * float(ref.abs().max()))
    out32 = diffuse_basis(normal.float(), _soa(wi).float(), falloff.float(), drive_k.float())
    torch.testing.assert_close(out32.double(), ref, rtol=1e-4, atol=1e-6 * float(ref.abs().max()))


def test_a_diffuse_basis_near_a_known_one_is_summed_again_only_where_an_emitter_crosses():
    frame, wi, _, ff, drive, _ = _case(5, N=40, V=6, M=60)
    known_normal, drive_k = frame[:, 2], drive[0, 0]
    known, margin = diffuse_basis_and_margin(known_normal, _soa(wi), ff, drive_k)
    cos = (wi * known_normal[:, None, None]).sum(-1).abs()
    ref_margin = torch.where(ff != 0, cos, torch.full_like(cos, math.inf)).amin(-1)
    torch.testing.assert_close(margin, ref_margin)
    g = torch.Generator().manual_seed(6)
    for tilt in (1e-4, 0.03, 0.3):  # from no entry crossing to most
        normal = safe_normalize(known_normal + tilt * torch.randn(known_normal.shape, generator=g, dtype=wi.dtype))
        whole = diffuse_basis(normal, _soa(wi), ff, drive_k)
        assert torch.equal(diffuse_basis_near(normal, _soa(wi), ff, drive_k, known, known_normal, margin), whole)
        changed = (whole != known).flatten(2).any(-1).float().mean()
        assert (changed == 0) if tilt < 1e-3 else (changed > 0)


def _tabulated(scanner):
    angles = np.linspace(0.0, 90.0, 7)
    values = np.cos(np.radians(angles)) ** 1.5 + 0.05  # light up to 90 deg: still dark behind
    return dataclasses.replace(scanner, angular_kind="table", angular_table=np.stack([angles, values], 1))


@pytest.mark.parametrize("device", [load_scanner, lambda: _tabulated(load_scanner())], ids=["led_array", "psi_table"])
def test_emitter_directions_are_the_emitter_geometry(device):
    scanner = device()
    g = torch.Generator().manual_seed(4)
    d = torch.float64
    M = 40
    x = torch.randn(M, 3, generator=g, dtype=d) * 0.03 + torch.tensor([0.0, 0.0, 0.12], dtype=d)
    x[::8] = x[::8] * torch.tensor([1.0, 1.0, 0.0], dtype=d) - torch.tensor([0.0, 0.0, 0.02], dtype=d)  # behind
    n = safe_normalize(torch.randn(M, 3, generator=g, dtype=d) * 0.5 + torch.tensor([0.0, 0.0, -1.0], dtype=d))
    t = torch.randn(M, 3, generator=g, dtype=d)
    live = torch.rand(M, generator=g) > 0.2
    frame = frame_from_normal_tangent(n, t)
    wo, wi, falloff = emitter_directions(scanner, x, frame, live, padding=True)
    geo = local_emitter_geometry(scanner, x, n, t)
    K = geo.falloff.shape[1]
    assert wi.shape == (M, 3, K + 1) and falloff.shape == (M, K + 1) and wo.dtype == torch.float64
    want_f = geo.falloff * live[:, None]
    for got, want in ((wo, geo.wo_l), (wi[:, :, :K], _soa(geo.wi_l)), (falloff[:, :K], want_f)):
        torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-12 * float(want.abs().max()))
    assert (falloff[:, K] == 0).all() and torch.equal(wi[:, :, K], wi[:, :, 0])
    assert float(falloff.max()) > 0 and (falloff[~live] == 0).all()
    wo32, wi32, f32 = emitter_directions(scanner, x.float(), frame.float(), live, padding=False)
    assert wi32.shape == (M, 3, K) and f32.dtype == torch.float32
    torch.testing.assert_close(f32.double(), want_f, rtol=1e-5, atol=1e-7 * float(want_f.abs().max()))
