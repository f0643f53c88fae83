"""The compiled pixel bases equal their torch definitions (float64 references): the diffuse basis
the horizon-clipped sum over the emitters, the specular one the torch lobe summed, its derivatives
automatic differentiation of that, the per-emitter lobe weights the torch lobe, and their
per-sample inputs the emitter geometry."""

import dataclasses
import math

import numpy as np
import pytest
import torch

from ntp_engine.fit.pixel_bases import (
    diffuse_basis,
    diffuse_basis_and_margin,
    diffuse_basis_near,
    emitter_directions,
    lobe_weights,
    selected_emitters,
    specular_basis,
    specular_basis_and_derivatives,
)
from ntp_engine.physics.brdf import fresnel_schlick
from ntp_engine.physics.frame import frame_from_normal_tangent, rotation_from_vector, safe_normalize, to_local
from ntp_engine.physics.measurement import local_emitter_geometry
from ntp_engine.scanner.device_file import load_scanner


def _lobe(frame: torch.Tensor, wi, h, wo, fresnel_falloff, alpha) -> torch.Tensor:
    """The torch definition the compiled loops are checked against: Eq. 1's specular weight per
    emitter, F D G / (4 cos_i cos_o) (wi.n)+ * falloff, ``(N, V, K)``, for shading frames ``frame
    (N, 3, 3)`` (rows t, b, n in the geometric frame), geometric-frame ``wi, h (N, V, K, 3)``, ``wo
    (N, V, 3)`` and ``alpha (N, 2)`` — the cancelled Smith form of ``physics.brdf.ggx_specular``
    (F depends on wi.h only, so it comes precomputed with the falloff)."""
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


def _case(seed: int, N=6, V=5, M=40):
    g = torch.Generator().manual_seed(seed)
    d = torch.float64
    n = safe_normalize(torch.tensor([0.0, 0.0, 1.0], dtype=d) + 0.3 * torch.randn(N, 3, generator=g, dtype=d))
    frame = frame_from_normal_tangent(n, torch.randn(N, 3, generator=g, dtype=d))
    wi = safe_normalize(torch.randn(N, V, M, 3, generator=g, dtype=d) + torch.tensor([0, 0, 1.2], dtype=d))
    wo = safe_normalize(torch.randn(N, V, 3, generator=g, dtype=d) + torch.tensor([0, 0, 1.5], dtype=d))
    h = safe_normalize(wi + wo[:, :, None])
    ff = fresnel_schlick((wi * h).sum(-1)) * torch.rand(N, V, M, generator=g, dtype=d)
    ff[:, :, -3:] = 0.0  # padding emitters: no light
    drive = torch.rand(N, V, M, 3, generator=g, dtype=d)
    alpha = torch.exp(torch.empty(N, 2, dtype=d).uniform_(math.log(0.02), math.log(0.5), generator=g))
    return frame, wi, h, wo, ff, drive, alpha


def _reference(frame, wi, h, wo, ff, drive, alpha, x):
    """The torch lobe summed over emitters, at shading-frame rotation x[:, :3] and log-alpha offsets x[:, 3:]."""
    f = rotation_from_vector(x[:, :3]).transpose(-1, -2) @ frame
    lobe = _lobe(f, wi, h, wo, ff, alpha * x[:, 3:].exp())
    return torch.einsum("nvm,nvmc->nvc", lobe, drive)


@pytest.mark.parametrize("seed", [0, 1])
def test_bases_and_derivatives_match_the_torch_lobe(seed):
    frame, wi, h, wo, ff, drive, alpha = _case(seed)
    spec, ds = specular_basis_and_derivatives(frame, wi, h, wo, ff, drive, alpha)
    x0 = torch.zeros(len(frame), 5, dtype=torch.float64)
    ref = _reference(frame, wi, h, wo, ff, drive, alpha, x0)
    assert ref.abs().max() > 0
    assert spec.dtype == ds.dtype == torch.float64  # the scipy baseline differentiates them numerically
    torch.testing.assert_close(spec, ref, rtol=1e-9, atol=1e-12 * float(ref.abs().max()))
    assert torch.equal(specular_basis(frame, wi, h, wo, ff, drive, alpha), spec)
    args32 = [x.float() for x in (frame, wi, h, wo, ff, drive, alpha)]
    spec32, ds32 = specular_basis_and_derivatives(*args32)
    assert spec32.dtype == ds32.dtype == torch.float32
    torch.testing.assert_close(spec32.double(), ref, rtol=1e-4, atol=1e-6 * float(ref.abs().max()))
    # forward-mode derivatives by each of the 5 parameters
    for k in range(5):
        e = torch.zeros_like(x0)
        e[:, k] = 1.0
        _, jvp = torch.func.jvp(lambda x: _reference(frame, wi, h, wo, ff, drive, alpha, x), (x0,), (e,))
        scale = float(jvp.abs().max())
        torch.testing.assert_close(ds[:, :, k], jvp, rtol=1e-8, atol=1e-11 * scale)
        torch.testing.assert_close(ds32[:, :, k].double(), jvp, rtol=1e-3, atol=1e-5 * scale)


def test_a_widened_lobe_is_the_lobe_each_entry_sees_derived_by_the_surfaces_alphas():
    """With ``widening (N, V, 2)``, entry v sees alphas sqrt(alpha^2 + widening[:, v]) (``fit.
    footprint``); the derivatives stay those by the surface's own log alphas."""
    frame, wi, h, wo, ff, drive, alpha = _case(4)
    g = torch.Generator().manual_seed(9)
    wide = 0.01 * torch.rand(*wo.shape[:2], 2, generator=g, dtype=torch.float64)

    def reference(x):
        f = rotation_from_vector(x[:, :3]).transpose(-1, -2) @ frame
        a = alpha * x[:, 3:].exp()
        out = []
        for v in range(wo.shape[1]):
            seen = torch.sqrt(a**2 + wide[:, v])
            sl = slice(v, v + 1)
            lobe = _lobe(f, wi[:, sl], h[:, sl], wo[:, sl], ff[:, sl], seen)
            out.append(torch.einsum("nvm,nvmc->nvc", lobe, drive[:, sl]))
        return torch.cat(out, 1)

    x0 = torch.zeros(len(frame), 5, dtype=torch.float64)
    spec, ds = specular_basis_and_derivatives(frame, wi, h, wo, ff, drive, alpha, None, wide)
    ref = reference(x0)
    torch.testing.assert_close(spec, ref, rtol=1e-9, atol=1e-12 * float(ref.abs().max()))
    assert not torch.allclose(spec, specular_basis(frame, wi, h, wo, ff, drive, alpha))
    assert torch.equal(specular_basis(frame, wi, h, wo, ff, drive, alpha, None, wide), spec)
    for k in range(5):
        e = torch.zeros_like(x0)
        e[:, k] = 1.0
        _, jvp = torch.func.jvp(reference, (x0,), (e,))
        torch.testing.assert_close(ds[:, :, k], jvp, rtol=1e-8, atol=1e-11 * float(jvp.abs().max()))


def test_lobe_weights_are_the_torch_lobe_per_emitter():
    frame, wi, h, wo, ff, _, alpha = _case(3)
    wo[0, 1] = wo[0, 1] * torch.tensor([1.0, 1.0, -1.0], dtype=wo.dtype)  # seen from below: no lobe
    ref = _lobe(frame, wi, h, wo, ff, alpha)
    got = lobe_weights(frame, wi, h, wo, ff, alpha)
    assert got.dtype == torch.float64 and (ref > 0).any() and (ref == 0).any()
    torch.testing.assert_close(got, ref, rtol=1e-10, atol=1e-14 * float(ref.max()))
    assert torch.equal(got == 0, ref == 0)  # the same emitters score nothing: blocks rank the same
    got32 = lobe_weights(*(x.float() for x in (frame, wi, h, wo, ff, alpha)))
    assert got32.dtype == torch.float32
    torch.testing.assert_close(got32.double(), ref, rtol=1e-4, atol=1e-6 * float(ref.max()))


def test_rows_read_a_subset_without_copying_it():
    frame, wi, h, wo, ff, drive, alpha = _case(5)
    rows = torch.tensor([4, 1, 1, 3])  # any order, repeats allowed
    spec, ds = specular_basis_and_derivatives(frame[rows], wi, h, wo, ff, drive, alpha[rows], rows)
    want, want_ds = specular_basis_and_derivatives(
        frame[rows], wi[rows], h[rows], wo[rows], ff[rows], drive[rows], alpha[rows]
    )
    assert torch.equal(spec, want) and torch.equal(ds, want_ds) and want.abs().max() > 0
    assert torch.equal(specular_basis(frame[rows], wi, h, wo, ff, drive, alpha[rows], rows), want)
    # the diffuse basis (and its horizon margins), the block ranking and the emitter selection too
    n, drive_k = frame[rows, 2], drive[0, 0]
    got, margin = diffuse_basis_and_margin(n, wi, ff, drive_k, rows)
    want, want_margin = diffuse_basis_and_margin(n, wi[rows], ff[rows], drive_k)
    assert torch.equal(got, want) and torch.equal(margin, want_margin) and want.abs().max() > 0
    tilted = safe_normalize(n + 0.2)
    assert torch.equal(
        diffuse_basis_near(tilted, wi, ff, drive_k, got, n, margin, rows),
        diffuse_basis(tilted, wi[rows], ff[rows], drive_k),
    )
    want = lobe_weights(frame[rows], wi[rows], h[rows], wo[rows], ff[rows], alpha[rows])
    assert torch.equal(lobe_weights(frame[rows], wi, h, wo, ff, alpha[rows], rows), want)
    order = want[..., :8].argsort(-1, descending=True)  # 8 blocks of 5 samples
    members = torch.arange(40).view(8, 5)
    fine, coarse = (wi, h, ff, drive[0, 0, :40]), (wi[:, :, :8], h[:, :, :8], ff[:, :, :8], drive[0, 0, :8])
    got = selected_emitters(order, members, 2, fine, coarse, rows)
    picked = (wi[rows], h[rows], ff[rows], drive[0, 0, :40])
    want = selected_emitters(order, members, 2, picked, tuple(x[rows] for x in coarse[:3]) + coarse[3:])
    assert all(torch.equal(a, b) for a, b in zip(got, want))


def test_selected_emitters_are_the_expanded_blocks_then_the_coarse_ones():
    g = torch.Generator().manual_seed(6)
    N, V, K, C, S, B = 3, 4, 20, 5, 4, 2
    members = torch.randperm(K, generator=g)[: C * S].view(C, S)
    members[-1, -1] = K - 1  # a padding-like index: any sample
    fine = (
        torch.randn(N, V, K, 3, generator=g),
        torch.randn(N, V, K, 3, generator=g),
        torch.rand(N, V, K, generator=g),
        torch.rand(K, 3, generator=g),
    )
    coarse = (
        torch.randn(N, V, C, 3, generator=g),
        torch.randn(N, V, C, 3, generator=g),
        torch.rand(N, V, C, generator=g),
        torch.rand(C, 3, generator=g),
    )
    order = torch.stack([torch.randperm(C, generator=g) for _ in range(N * V)]).view(N, V, C)
    wi, h, ff, drive = selected_emitters(order, members, B, fine, coarse)
    assert wi.shape == (N, V, B * S + C - B, 3) and drive.shape == wi.shape and ff.shape == wi.shape[:3]
    for n in range(N):
        for v in range(V):
            k = members[order[n, v, :B]].flatten()
            c = order[n, v, B:]
            for got, f, co, per_entry in (
                (wi, fine[0], coarse[0], True),
                (h, fine[1], coarse[1], True),
                (ff, fine[2], coarse[2], True),
                (drive, fine[3], coarse[3], False),
            ):
                want = torch.cat([f[n, v, k], co[n, v, c]]) if per_entry else torch.cat([f[k], co[c]])
                assert torch.equal(got[n, v], want)


def test_no_light_and_views_from_below_give_zero():
    frame, wi, h, wo, ff, drive, alpha = _case(2)
    ff = torch.zeros_like(ff)
    spec, ds = specular_basis_and_derivatives(frame, wi, h, wo, ff, drive, alpha)
    assert not spec.any() and not ds.any()
    frame, wi, h, wo, ff, drive, alpha = _case(3)
    below = -wo  # every view under the shading frame's horizon... for frames near +z
    below[..., 2] = -below[..., 2].abs() - 0.5
    spec, ds = specular_basis_and_derivatives(frame, wi, h, safe_normalize(below), ff, drive, alpha)
    assert not spec.any() and not ds.any() and torch.isfinite(ds).all()


def test_diffuse_basis_sums_the_emitters_above_the_horizon():
    frame, wi, _, _, ff, drive, _ = _case(4)
    normal, falloff, drive_k = frame[:, 2], ff, drive[0, 0]  # one drive per emitter for every entry
    above = ((wi * normal[:, None, None]).sum(-1) > 0).double() * falloff
    ref = torch.einsum("nvk,kc,nvkj->nvcj", above, drive_k, wi) / math.pi
    out = diffuse_basis(normal, wi, falloff, drive_k)
    assert out.shape == ref.shape and (above == 0).any() and ref.abs().max() > 0
    torch.testing.assert_close(out, ref, rtol=1e-9, atol=1e-12 * float(ref.abs().max()))
    out32 = diffuse_basis(normal.float(), wi.float(), falloff.float(), drive_k.float())
    torch.testing.assert_close(out32.double(), ref, rtol=1e-4, atol=1e-6 * float(ref.abs().max()))


def test_a_diffuse_basis_near_a_known_one_is_summed_again_only_where_an_emitter_crosses():
    frame, wi, _, _, ff, drive, _ = _case(5, N=40, V=6, M=60)
    known_normal, drive_k = frame[:, 2], drive[0, 0]
    known, margin = diffuse_basis_and_margin(known_normal, wi, ff, drive_k)
    cos = (wi * known_normal[:, None, None]).sum(-1).abs()
    ref_margin = torch.where(ff != 0, cos, torch.full_like(cos, math.inf)).amin(-1)
    torch.testing.assert_close(margin, ref_margin)
    g = torch.Generator().manual_seed(6)
    for tilt in (1e-4, 0.03, 0.3):  # from no entry crossing to most
        normal = safe_normalize(known_normal + tilt * torch.randn(known_normal.shape, generator=g, dtype=wi.dtype))
        whole = diffuse_basis(normal, wi, ff, drive_k)
        assert torch.equal(diffuse_basis_near(normal, wi, ff, drive_k, known, known_normal, margin), whole)
        changed = (whole != known).flatten(2).any(-1).float().mean()
        assert (changed == 0) if tilt < 1e-3 else (changed > 0)


def _tabulated(scanner):
    angles = np.linspace(0.0, 90.0, 7)
    values = np.cos(np.radians(angles)) ** 1.5 + 0.05  # light up to 90 deg: still dark behind
    return dataclasses.replace(scanner, angular_kind="table", angular_table=np.stack([angles, values], 1))


@pytest.mark.parametrize("device", [load_scanner, lambda: _tabulated(load_scanner())], ids=["led_array", "psi_table"])
def test_emitter_directions_are_the_emitter_geometry_with_half_vectors(device):
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
    wo, wi, h, falloff, ff = emitter_directions(scanner, x, frame, live, padding=True)
    geo = local_emitter_geometry(scanner, x, n, t)
    K = geo.falloff.shape[1]
    assert wi.shape == (M, K + 1, 3) and falloff.shape == (M, K + 1) and wo.dtype == torch.float64
    want_h = safe_normalize(geo.wi_l + geo.wo_l[:, None])
    want_f = geo.falloff * live[:, None]
    for got, want in (
        (wo, geo.wo_l),
        (wi[:, :K], geo.wi_l),
        (h[:, :K], want_h),
        (falloff[:, :K], want_f),
        (ff[:, :K], fresnel_schlick((geo.wi_l * want_h).sum(-1)) * want_f),
    ):
        torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-12 * float(want.abs().max()))
    assert (falloff[:, K] == 0).all() and (ff[:, K] == 0).all() and torch.equal(wi[:, K], wi[:, 0])
    assert float(falloff.max()) > 0 and (falloff[~live] == 0).all()
    wo32, wi32, _, f32, _ = emitter_directions(scanner, x.float(), frame.float(), live, padding=False)
    assert wi32.shape == (M, K, 3) and f32.dtype == torch.float32
    torch.testing.assert_close(f32.double(), want_f, rtol=1e-5, atol=1e-7 * float(want_f.abs().max()))
