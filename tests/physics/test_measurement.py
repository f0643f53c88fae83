"""Eq. 1 measurements against closed forms for point, linear and area emitters; Eq. 6 confidence."""

import dataclasses
import math

import numpy as np
import torch

from ntp_engine.io.assets import DEVICES_DIR
from ntp_engine.physics.brdf import ggx
from ntp_engine.physics.measurement import measure, physical_lumitexel
from ntp_engine.scanner.device_file import load_scanner

F64 = torch.float64
ZERO = torch.zeros(3, dtype=F64)


def _t(*v):
    return torch.tensor(v if len(v) > 1 else v[0], dtype=F64)


def _diffuse_B(device, x, n, rho=0.5, visibility=None):
    t = torch.linalg.cross(n, _t(0.3, 1.0, 0.2), dim=-1)
    m = physical_lumitexel(
        device, x, n, t, torch.full((3,), rho, dtype=F64), ZERO, _t(0.1), _t(0.1), visibility=visibility
    )
    return measure(device, m)


def _single_emitter(kind, pos, normal, axis, size=(0.0, 0.0)):
    base = load_scanner(DEVICES_DIR / f"{kind}_light.toml")
    return dataclasses.replace(
        base,
        emitter_positions=np.array([pos], float),
        emitter_normals=np.array([normal], float),
        emitter_axes=np.array([axis], float),
        emitter_size=np.array(size, float),
    )


def test_diffuse_patch_under_point_light_is_lambert_inverse_square():
    dev = _single_emitter("point", (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0))
    # head-on at 30 cm
    B = _diffuse_B(dev, _t(0.0, 0.0, 0.3), _t(0.0, 0.0, -1.0))
    torch.testing.assert_close(B, torch.full((3,), 0.5 / math.pi / 0.09, dtype=F64))
    # off axis: the light sees the point at 30 deg (cosine lobe), the patch is tilted 20 deg from it
    r, th = 0.25, math.radians(30)
    x = _t(r * math.sin(th), 0.0, r * math.cos(th))
    to_light = -x / r
    tilt = math.radians(20)
    n = to_light * math.cos(tilt) + _t(0.0, 1.0, 0.0) * math.sin(tilt)
    B = _diffuse_B(dev, x, n)
    expect = 0.5 / math.pi * math.cos(tilt) * math.cos(th) / r**2
    torch.testing.assert_close(B, torch.full((3,), expect, dtype=F64))


def test_area_light_matches_configuration_factor():
    a, b, d = 0.32, 0.16, 0.3
    dev = _single_emitter("area", (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (a, b))

    def corner(x, y):  # point-to-rectangle factor, point above a corner of an x-by-y rectangle
        X, Y = x / d, y / d
        return (
            X / math.sqrt(1 + X * X) * math.atan(Y / math.sqrt(1 + X * X))
            + Y / math.sqrt(1 + Y * Y) * math.atan(X / math.sqrt(1 + Y * Y))
        ) / (2 * math.pi)

    F = 4 * corner(a / 2, b / 2)
    # radiance of a unit-intensity emitter spread over area A is 1/A; E = pi L F; B = rho/pi E
    B = _diffuse_B(dev, _t(0.0, 0.0, d), _t(0.0, 0.0, -1.0))
    torch.testing.assert_close(B, torch.full((3,), 0.5 * F / (a * b), dtype=F64), rtol=1e-5, atol=0)


def test_linear_light_matches_closed_form():
    half, d = 0.16, 0.3
    dev = _single_emitter("linear", (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (2 * half, 0.0))
    E = (half / (d * d + half * half) + math.atan(half / d) / d) / (2 * half)
    B = _diffuse_B(dev, _t(0.0, 0.0, d), _t(0.0, 0.0, -1.0))
    torch.testing.assert_close(B, torch.full((3,), 0.5 / math.pi * E, dtype=F64), rtol=1e-6, atol=0)


def test_physical_lumitexel_matches_per_emitter_formula():
    dev = load_scanner()
    x = _t(0.02, -0.01, 0.32)
    n = torch.nn.functional.normalize(_t(0.1, -0.3, -1.0), dim=0)
    t = torch.nn.functional.normalize(torch.linalg.cross(n, _t(0.0, 1.0, 0.0), dim=0), dim=0)
    b = torch.linalg.cross(n, t, dim=0)
    rd, rs, ax, ay = _t(0.2, 0.4, 0.6), _t(3.0, 2.0, 1.0), _t(0.05), _t(0.2)
    m = physical_lumitexel(dev, x, n, t, rd, rs, ax, ay)
    assert m.shape == (512, 3)
    fr = torch.stack([t, b, n])
    wo = -x / x.norm()
    for led in (0, 100, 255, 511):
        d = torch.as_tensor(dev.emitter_positions[led]) - x
        r = d.norm()
        wi = d / r
        cos_l = float(-wi @ torch.as_tensor(dev.emitter_normals[led]))
        expect = ggx(fr @ wi, fr @ wo, rd, rs, ax, ay) * max(float(wi @ n), 0) * max(cos_l, 0) / r**2
        torch.testing.assert_close(m[led], expect)


def test_pattern_color_matrix_and_visibility():
    dev = load_scanner()
    x, n = _t(0.0, 0.0, 0.31), _t(0.0, 0.2, -1.0) / math.sqrt(1.04)
    dev.color_matrix = np.array([[0, 1.0, 0], [0, 0, 1.0], [1.0, 0, 0]])  # camera R sees LED G, ...
    green = torch.zeros(512, 3, dtype=F64)
    green[:, 1] = 1.0
    t = _t(1.0, 0.0, 0.0)
    m = physical_lumitexel(dev, x, n, t, torch.ones(3, dtype=F64), ZERO, _t(0.1), _t(0.1))
    B = measure(dev, m, green)
    assert B[0] > 0 and B[1] == 0 and B[2] == 0, B
    p1, p2 = torch.rand(2, 512, 3, dtype=F64)
    torch.testing.assert_close(measure(dev, m, p1 + p2), measure(dev, m, p1) + measure(dev, m, p2))
    assert measure(dev, m[:, :1], p1).shape == (1,)
    # a visibility hook that blocks the left half of the panel removes exactly those LEDs
    left = torch.as_tensor(dev.emitter_positions[:, 0] < 0)
    blocked = physical_lumitexel(
        dev,
        x,
        n,
        t,
        torch.ones(3, dtype=F64),
        ZERO,
        _t(0.1),
        _t(0.1),
        visibility=lambda pts, q: (~left)[:, None].to(F64),
    )
    torch.testing.assert_close(blocked, m * (~left)[:, None])
    zero = physical_lumitexel(
        dev, x, n, t, torch.ones(3, dtype=F64), ZERO, _t(0.1), _t(0.1), visibility=torch.zeros(512, 1, dtype=F64)
    )
    assert (zero == 0).all()


def test_float32_agrees_with_float64_in_batches():
    dev = load_scanner()
    gen = torch.Generator().manual_seed(3)
    x = torch.as_tensor(dev.valid_center) + 0.05 * torch.randn(4, 5, 3, generator=gen, dtype=F64)
    n = torch.nn.functional.normalize(-x + 0.2 * torch.randn(4, 5, 3, generator=gen, dtype=F64), dim=-1)
    t = torch.randn(4, 5, 3, generator=gen, dtype=F64)
    args = (
        torch.rand(4, 5, 3, generator=gen, dtype=F64),
        10 * torch.rand(4, 5, 3, generator=gen, dtype=F64),
        torch.full((4, 5), 0.02, dtype=F64),
        torch.full((4, 5), 0.3, dtype=F64),
    )
    B64 = measure(dev, physical_lumitexel(dev, x, n, t, *args))
    B32 = measure(dev, physical_lumitexel(dev, *(v.float() for v in (x, n, t, *args))))
    assert B64.shape == (4, 5, 3) and B32.dtype == torch.float32
    torch.testing.assert_close(B32.double(), B64, rtol=1e-4, atol=1e-4)


def test_float32_gradients_reach_pattern_and_geometry_at_the_edges():
    dev = load_scanner()
    x = torch.tensor([[0.0, 0.0, 0.31], [0.07, -0.07, 0.38]], requires_grad=True)
    # one normal facing the camera, one exactly edge-on to it (grazing view)
    n = torch.tensor([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0]], requires_grad=True)
    t = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    a = torch.tensor([0.006, 0.5], requires_grad=True)
    logits = torch.zeros(512, 3, requires_grad=True)
    m = physical_lumitexel(dev, x, n, t, torch.full((2, 3), 0.5), torch.full((2, 3), 10.0), a, a.flip(0))
    B = measure(dev, m, torch.sigmoid(logits))
    assert torch.isfinite(B).all() and (B >= 0).all()
    B.sum().backward()
    for leaf in (x, n, a, logits):
        assert torch.isfinite(leaf.grad).all()
    assert logits.grad.abs().sum() > 0


def test_factorised_measurement_equals_the_reference():
    from ntp_engine.physics.measurement import measurement_rgb

    for name in ("ntp_led_32x16", "area_light"):
        dev = load_scanner(DEVICES_DIR / f"{name}.toml")
        gen = torch.Generator().manual_seed(8)
        x = torch.as_tensor(dev.valid_center) + 0.05 * torch.randn(7, 3, generator=gen, dtype=F64)
        n = torch.nn.functional.normalize(-x + 0.3 * torch.randn(7, 3, generator=gen, dtype=F64), dim=-1)
        t = torch.randn(7, 3, generator=gen, dtype=F64)
        rd, rs = torch.rand(7, 3, generator=gen, dtype=F64), 10 * torch.rand(7, 3, generator=gen, dtype=F64)
        ax, ay = torch.full((7,), 0.05, dtype=F64), torch.full((7,), 0.2, dtype=F64)
        p = torch.rand(dev.num_emitters, 3, generator=gen, dtype=F64)
        L, Q = dev.emitter_samples()[1].shape
        vis = (torch.rand(7, L, Q, generator=gen) > 0.3).to(F64)
        ref = measure(dev, physical_lumitexel(dev, x, n, t, rd, rs, ax, ay, visibility=vis), p)
        torch.testing.assert_close(measurement_rgb(dev, x, n, t, rd, rs, ax, ay, p, vis), ref)
