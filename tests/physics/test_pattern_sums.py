"""The fused per-emitter sums against the tensor reference (measurement, confidence)."""

import dataclasses

import numpy as np
import pytest
import torch

from ntp_engine.io.assets import DEVICES_DIR
from ntp_engine.physics.confidence import specular_peak
from ntp_engine.physics.frame import safe_normalize
from ntp_engine.physics.measurement import local_emitter_geometry, specular_lobe, terms_from_lobe
from ntp_engine.physics.pattern_sums import pattern_sums
from ntp_engine.scanner.device_file import load_scanner

F64 = torch.float64


def _entries(M=300, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(M, 3, generator=g, dtype=F64) * 0.03 + torch.tensor([0.0, 0.0, 0.12], dtype=F64)
    n = safe_normalize(torch.randn(M, 3, generator=g, dtype=F64) * 0.6 + torch.tensor([0.0, 0.0, -1.0], dtype=F64))
    t = safe_normalize(torch.randn(M, 3, generator=g, dtype=F64))
    ax = torch.rand(M, generator=g, dtype=F64) * 0.494 + 0.006  # the whole alpha range
    ay = ax * (torch.rand(M, generator=g, dtype=F64) * 0.9 + 0.1)
    # a tenth behind the emitters' plane, facing them: the samples light them from behind (Psi = 0)
    back = torch.arange(M) % 10 == 3
    x[back] = x[back] * torch.tensor([1.0, 1.0, 0.0], dtype=F64) - torch.tensor([0.0, 0.0, 0.02], dtype=F64)
    n[back] = safe_normalize(n[back] * torch.tensor([1.0, 1.0, -1.0], dtype=F64))
    return x, n, t, ax, ay


def _reference(scanner, x, n, t, ax, ay):
    geo = local_emitter_geometry(scanner, x, n, t)
    spec = specular_lobe(geo, ax, ay)
    a_l, s_l = terms_from_lobe(geo, spec)
    drive = torch.as_tensor(scanner.effective_pattern(), dtype=F64)
    return a_l @ drive, s_l @ drive, spec.amax(-1), specular_peak(geo.wo_l, ax, ay)


def _tabulated(scanner, last_deg=80.0):
    angles = np.linspace(0.0, last_deg, 9)
    values = np.cos(np.radians(angles)) ** 1.5 + 0.05  # light up to the table's end: 90 deg included
    return dataclasses.replace(scanner, angular_kind="table", angular_table=np.stack([angles, values], 1))


@pytest.mark.parametrize(
    "device",
    [
        lambda: load_scanner(),
        lambda: dataclasses.replace(load_scanner(), angular_exponent=2.0),
        lambda: dataclasses.replace(load_scanner(), angular_exponent=0.0),  # 0^0: still dark behind
        lambda: _tabulated(load_scanner()),
        lambda: _tabulated(load_scanner(), last_deg=90.0),  # still dark behind
        lambda: load_scanner(DEVICES_DIR / "area_light.toml"),
    ],
    ids=["led_array", "cosine_power", "uniform", "psi_table", "psi_table_to_90", "area_light"],
)
def test_fused_sums_equal_the_tensor_reference(device):
    scanner = device()
    x, n, t, ax, ay = _entries()
    mask = torch.ones(len(x), dtype=torch.bool)
    mask[::7] = False
    got = pattern_sums(scanner, x, n, t, ax, ay, mask)
    want = _reference(scanner, x, n, t, ax, ay)
    for name, a, b in zip(("diffuse", "specular", "lobe_max", "lobe_peak"), dataclasses.astuple(got), want):
        b = torch.where(mask.reshape(-1, *([1] * (b.dim() - 1))), b, torch.zeros_like(b))
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12 * float(b.abs().max()), msg=name)
    assert float(got.specular.abs().max()) > 0 and float(got.diffuse.abs().max()) > 0
    assert (got.diffuse[~mask] == 0).all() and torch.isfinite(got.lobe_peak).all()


def test_fused_sums_of_views_facing_away_or_backlit_are_zero_and_finite():
    scanner = load_scanner()
    x, n, t, ax, ay = _entries(M=8)
    got = pattern_sums(scanner, x, -n, t, ax, ay, torch.ones(8, dtype=torch.bool))  # normals face away
    want = _reference(scanner, x, -n, t, ax, ay)
    assert (got.diffuse == 0).all() and (got.specular == 0).all() and (got.lobe_peak == 0).all()
    torch.testing.assert_close(got.lobe_max, want[2])


def test_fused_sums_weigh_each_emitter_sample_by_its_visibility():
    scanner = load_scanner(DEVICES_DIR / "area_light.toml")  # several samples per emitter
    x, n, t, ax, ay = _entries(M=64, seed=1)
    L, Q = scanner.emitter_samples(F64)[1].shape
    g = torch.Generator().manual_seed(2)
    vis = (torch.rand(64, L, Q, generator=g, dtype=F64) > 0.4).to(F64)
    vis[5] = 0.0  # an entry in full shadow
    vis[6] = 0.5  # a fractional one
    mask = torch.ones(64, dtype=torch.bool)
    got = pattern_sums(scanner, x, n, t, ax, ay, mask, visibility=vis.reshape(64, -1).numpy())
    geo = local_emitter_geometry(scanner, x, n, t, vis)
    a_l, s_l = terms_from_lobe(geo, specular_lobe(geo, ax, ay))
    drive = torch.as_tensor(scanner.effective_pattern(), dtype=F64)
    torch.testing.assert_close(got.diffuse, a_l @ drive, rtol=1e-9, atol=1e-14)
    torch.testing.assert_close(got.specular, s_l @ drive, rtol=1e-9, atol=1e-14)
    assert (got.diffuse[5] == 0).all() and float(got.diffuse.abs().max()) > 0
    unshadowed = pattern_sums(scanner, x, n, t, ax, ay, mask)
    torch.testing.assert_close(got.lobe_max, unshadowed.lobe_max)  # how bright toward a sample, lit or not
    # without the peaks: the same sums, no lobe maximum or peak
    bare = pattern_sums(scanner, x, n, t, ax, ay, mask, visibility=vis.reshape(64, -1).numpy(), peaks=False)
    assert torch.equal(bare.diffuse, got.diffuse) and torch.equal(bare.specular, got.specular)
    assert (bare.lobe_max == 0).all() and (bare.lobe_peak == 0).all()
    with pytest.raises(ValueError, match="visibility"):
        pattern_sums(scanner, x, n, t, ax, ay, mask, visibility=vis.reshape(64, -1)[:, :3].numpy())
