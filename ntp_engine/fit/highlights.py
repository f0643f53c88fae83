"""The unseen-highlight check: paper Eq. 6 recomputed from the *fitted* lobe and the trace's own
views. A texel whose beta is below ``BETA_MIN`` (no view ever saw its highlight) gets
``TexelFlag.NO_HIGHLIGHT`` and the fallback lobe (``FALLBACK_ALPHA`` isotropic): its trace does not
constrain the lobe, so the lobe is not guessed from the network's prior.

Convention: ``position, normal_geo, tangent_geo (N, V, 3)`` are each view's camera-space x, n^, t^;
``mask (N, V)`` the entries in the trace (padding's values are never used).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..physics.confidence import confidence
from ..physics.frame import frame_from_normal_tangent, to_world
from ..scanner.scanner import Scanner
from .flags import TexelFlag
from .geometry import FALLBACK_ALPHA, GeometryFit

BETA_MIN = 1e-3  # below this Eq. 6 confidence a texel's highlight was never observed
PARK_POSITION = (0.0, 0.0, 0.3)  # m, in front of the camera: where padded entries are evaluated


def parked_positions(position: Tensor, mask: Tensor) -> Tensor:
    """``position (N, V, 3)`` with padded entries moved to ``PARK_POSITION`` (finite everywhere)."""
    return torch.where(mask[..., None], position, torch.tensor(PARK_POSITION, dtype=position.dtype))


def frame_in_views(geometry: GeometryFit, normal_geo: Tensor, tangent_geo: Tensor) -> tuple[Tensor, Tensor]:
    """The fitted shading frame (lumitexel frame) in each view's camera space ``(N, V, 3)``."""
    dtype = normal_geo.dtype
    geo = frame_from_normal_tangent(normal_geo, tangent_geo)  # (N, V, 3, 3) rows t^, b^, n^
    n_cam = to_world(geometry.normal.to(dtype)[:, None, :], geo)
    t_cam = to_world(geometry.tangent.to(dtype)[:, None, :], geo)
    return n_cam, t_cam


def flag_unseen_highlights(
    scanner: Scanner, position: Tensor, normal_geo: Tensor, tangent_geo: Tensor, mask: Tensor, geometry: GeometryFit
) -> Tensor:
    """Eq. 6 recomputed from the *fitted* lobe and the trace's own views; texels whose beta is
    below ``BETA_MIN`` (no view ever saw the highlight) get ``TexelFlag.NO_HIGHLIGHT`` and the fallback
    lobe (alpha 0.3 isotropic; rho_s then comes from the albedo least squares with that lobe).
    Updates ``geometry`` in place; returns beta ``(N,)``."""
    n_cam, t_cam = frame_in_views(geometry, normal_geo, tangent_geo)
    x = parked_positions(position, mask)
    beta = confidence(
        scanner,
        x,
        n_cam,
        t_cam,
        geometry.alpha_x.to(x.dtype),
        geometry.alpha_y.to(x.dtype),
        geometry.rho_s.to(x.dtype),
        valid=mask,
    )
    fall_back_where_unseen(geometry, beta)
    return beta


def fall_back_where_unseen(geometry: GeometryFit, beta: Tensor) -> Tensor:
    """Texels with beta < BETA_MIN get the fallback lobe and TexelFlag.NO_HIGHLIGHT; returns that mask."""
    unseen = beta < BETA_MIN
    fa = torch.full_like(geometry.alpha_x, FALLBACK_ALPHA)
    geometry.alpha_x = torch.where(unseen, fa, geometry.alpha_x)
    geometry.alpha_y = torch.where(unseen, fa, geometry.alpha_y)
    geometry.flags = geometry.flags | unseen.long() * TexelFlag.NO_HIGHLIGHT
    return unseen
