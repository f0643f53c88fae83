"""What a pixel sample spans on the surface: the normals on a curved surface (the broader lobe it
therefore sees) and the albedos near an albedo edge (the neighbours' diffuse it blends in).

An entry's pixel value is a bilinear sample of the four pixels around the texel's projection
(``pipeline.traces``), and each pixel sees the surface at its own point. Where the surface turns
(the shape operator S, ``io.texels.shape_operators``) those points' normals differ from the
texel's: by S times the surface step of one pixel, about 1 mm at the scanner's distance — 6 deg on
a 9 mm tube. A lobe sharper than that spread (an alpha 0.006 lacquer spans 0.3 deg) is seen through
it: the mixture of the four points' lobes is, to second order, the lobe convolved with their slope
spread, which widens alpha^2 by a multiple of the slope variance along each axis (twice it for a
Gaussian spread of a Beckmann lobe, whose slope variance is alpha^2 / 2: Toksvig, LEAN mapping;
``TUNING.footprint.spread_widening``, chosen on the gallery). The mean normal is
the texel's (bilinear weights are unbiased), so the diffuse term is unchanged.

Convention: the texel's geometric frame (t^, b^, n^) as ``refine.policy``; slopes in radians (small
angles); ``spread (N, V, 2, 2)`` the covariance of the normal's (t^, b^) components over an entry's
bilinear sample: sum over the image axes a of f_a (1 - f_a) g_a g_a^T, f_a the sample's fraction
past the pixel centre and g_a = S (d x / d pixel_a) the normal's turn per pixel step. A camera whose
pixels integrate over their area would add 1/12 px^2 per axis; the gallery's renderers point-sample.

The same four points carry the albedo of the surface where they land, not the texel's: within a
pixel or two of an albedo edge (a texel is ~0.6 mm on the demo, a pixel ~0.5 mm) an entry's pixel
blends its neighbours' diffuse in a share that moves with the view's sub-pixel position, which a
per-texel model can explain only with a lobe (the demo's faint-lobe material: 61% of its texels
that kept a spurious lobe lie next to an albedo edge, 17% of all). ``albedo_blend`` says, per
entry, how much albedo the taps may blend in, read from an estimate of the albedo map: tap a lies
``delta`` (t^, b^ metres) from the texel's point — the pixel step (d x / d pixel) times its offset
from the sample — at uv + (d uv / d(t, b)) delta in the map (``io.texels.uv_per_metre``), and
the blend is sqrt(sum_a w_a d_a^2) with the sample's bilinear weights w_a and d_a the difference
from the texel's own albedo less ``TUNING.footprint.blend_noise`` (soft-thresholded: the estimate's own noise is no
edge). The refinement counts it as noise on the entry's diffuse light (``refine.policy``): an entry
that may blend a neighbour weighs less. Taking the blend out of the pixel instead (the estimate's
sum_a w_a d_a) needs the map exact below a texel: with the gallery's 128² estimates it cost the
vase 0.942 -> 0.826 of relit SSIM (docs/history/accuracy.md).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from ..io.maps import bilinear
from ..physics.frame import frame_from_normal_tangent
from ..scanner import camera
from ..scanner.scanner import Scanner
from .settings import TUNING


class Footprint(NamedTuple):
    """What each entry's pixel sample spans, as the refinement reads it (module docstring)."""

    spread: Tensor | None = None  # (N, V, 2, 2) slope spread (``slope_spread``); None: a flat surface
    albedo_blend: Tensor | None = None  # (N, V, 3) the neighbours' albedo it may blend in (``albedo_blend``)

    def rows(self, idx: Tensor | np.ndarray | slice) -> Footprint:
        """The same for the texels ``idx``."""
        return Footprint(*(None if v is None else v[idx] for v in self))


def _pixel_steps(scanner: Scanner, entries: Tensor, mask: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Per entry of ``entries (N, V, 12)`` with ``mask (N, V)``: the bilinear sample's fractions past
    the pixel centre ``(N, V, 2)`` (column, row), the surface step per pixel step along (t^, b^)
    ``(N, V, 2 tb, 2 px)`` (metres) and where both are defined ``(N, V)`` (live, not edge-on); float64."""
    dt = torch.float64
    x = entries[..., 3:6].to(dt)
    live = mask & (x[..., 2] > 0)
    x = torch.where(live[..., None], x, torch.tensor([0.0, 0.0, 1.0], dtype=dt))
    geo = frame_from_normal_tangent(entries[..., 6:9].to(dt), entries[..., 9:12].to(dt))  # (N, V, 3, 3)
    px = camera.project(scanner, x)  # (N, V, 2) column, row
    frac = px - torch.floor(px)
    # pixels per metre along t^, b^ on the tangent plane, and its inverse: metres per pixel step
    along = camera.project_jacobian(scanner, x) @ geo[..., :2, :].transpose(-1, -2)  # (N, V, 2 px, 2 tb)
    det = torch.linalg.det(along)
    seen = live & (det.abs() > 1e-12) & torch.isfinite(det)
    step = torch.linalg.inv(torch.where(seen[..., None, None], along, torch.eye(2, dtype=dt)))  # (N, V, 2 tb, 2 px)
    return frac, step, seen


def slope_spread(scanner: Scanner, entries: Tensor, mask: Tensor, shape_operator: Tensor) -> Tensor:
    """``spread (N, V, 2, 2)`` (module docstring) of trace ``entries (N, V, 12)`` (camera space,
    ``learn.ragged``'s layout) with ``mask (N, V)``, on texels whose shape operators are
    ``shape_operator (N, 2, 2)`` (1/m); 0 for padding and where the surface is seen edge-on."""
    frac, step, seen = _pixel_steps(scanner, entries, mask)
    var = frac * (1 - frac)  # per image axis, px^2
    turn = shape_operator.to(step.dtype)[:, None] @ step  # normal's (t, b) change per pixel step
    spread = turn @ torch.diag_embed(var) @ turn.transpose(-1, -2)
    spread = torch.where(seen[..., None, None], torch.nan_to_num(spread), torch.zeros_like(spread))
    scale = (TUNING.footprint.spread_max / (spread[..., 0, 0] + spread[..., 1, 1]).clamp_min(1e-30)).clamp_max(1.0)
    return _flushed((spread * scale[..., None, None]).to(entries.dtype))


def sample_points(scanner: Scanner, entries: Tensor, mask: Tensor) -> tuple[Tensor, Tensor]:
    """Where the four pixels of each entry's bilinear sample see the surface: ``delta (N, V, 4, 2)``
    in metres along (t^, b^) from the texel's point (on its tangent plane; the taps in
    ``io.maps.bilinear_corners``' order) and their weights ``(N, V, 4)`` (0 for padding and edge-on
    entries); float64."""
    frac, step, seen = _pixel_steps(scanner, entries, mask)
    fc, fr = frac[..., 0], frac[..., 1]
    # (column, row) of each tap from the sample, in pixels: r0c0, r0c1, r1c0, r1c1
    taps = torch.stack([torch.stack([c, r], -1) for r in (-fr, 1 - fr) for c in (-fc, 1 - fc)], -2)
    weight = torch.stack([wc * wr for wr in (1 - fr, fr) for wc in (1 - fc, fc)], -1)
    delta = torch.einsum("nvij,nvaj->nvai", step, taps)
    return torch.where(seen[..., None, None], delta, torch.zeros_like(delta)), weight * seen[..., None]


def tap_uv(delta: np.ndarray, uv: np.ndarray, uv_per_metre: np.ndarray) -> np.ndarray:
    """Where each tap ``delta (N, V, 4, 2)`` (``sample_points``, metres along (t^, b^)) of texels at
    ``uv (N, 2)`` with ``uv_per_metre (N, 2, 2)`` (``io.texels``) lands in the map: uv + (d uv /
    d(t, b)) delta, ``(N, V, 4, 2)`` (first order: on the texel's tangent plane)."""
    return uv[:, None, None, :] + np.einsum("nij,nvaj->nvai", uv_per_metre, delta)


def albedo_blend(delta: Tensor, weight: Tensor, uv: np.ndarray, uv_per_metre: np.ndarray, albedo: np.ndarray) -> Tensor:
    """How much of its neighbours' albedo each entry's pixel sample may blend in ``(N, V, 3)``:
    sqrt(sum_a w_a d_a^2), d_a = rho(uv_a) - rho(uv) soft-thresholded by ``TUNING.footprint.blend_noise``, over the
    taps ``delta (N, V, 4, 2)`` with weights ``weight (N, V, 4)`` (``sample_points``) of texels at
    ``uv (N, 2)`` with ``uv_per_metre (N, 2, 2)`` (``io.texels``), rho the map ``albedo (H, W,
    3)`` sampled bilinearly (its unobserved texels filled). 0 where no tap is weighed or the map is
    uniform within ``TUNING.footprint.blend_noise``."""
    N, V = weight.shape[:2]
    at = tap_uv(delta.numpy(), uv, uv_per_metre)
    taps = bilinear(albedo, at.reshape(-1, 2)).reshape(N, V, 4, -1)
    d = taps - bilinear(albedo, uv)[:, None, None, :]
    d = np.maximum(np.abs(d) - TUNING.footprint.blend_noise, 0.0)
    return torch.from_numpy(np.sqrt((weight.numpy()[..., None] * d * d).sum(2)))


def widening(spread: Tensor, frame: Tensor) -> Tensor:
    """What each entry's pixel sample adds to a lobe's alpha_x^2, alpha_y^2 ``(N, V, 2)``:
    ``TUNING.footprint.spread_widening`` times the slope variance of ``spread (N, V, 2, 2)`` along the shading axes
    t, b of ``frame (N, 3, 3)`` (rows t, b, n in the geometric frame; their tangent-plane parts).
    The lobe the sample sees has sqrt(alpha^2 + widening) (``refine.pixel_bases``)."""
    axes = frame[:, :2, :2].to(spread.dtype)  # (N, 2 axes, 2 tb)
    return TUNING.footprint.spread_widening * _flushed(torch.einsum("nai,nvij,naj->nva", axes, spread, axes))


def _flushed(variance: Tensor) -> Tensor:
    """``variance`` with values below ``TUNING.footprint.negligible`` set to 0: a flat face's round-off (~1e-30) made
    float32 subnormals, whose arithmetic is ~10x slower."""
    return torch.where(variance.abs() < TUNING.footprint.negligible, torch.zeros_like(variance), variance)
