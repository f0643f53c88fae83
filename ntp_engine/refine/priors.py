"""The refinement's priors: what a texel's parameters are pulled toward besides its photos — the
mesh's normal, an isotropic lobe, a grey lobe (``tint_scale``), and a basis material's lobe
(``LobePrior``) — as penalties in half chi-square units added to the data cost.

Convention: parameters as ``refine.model`` (geometric frame, log alphas, RGB albedos); ``frame
(N, 3, 3)`` rows (t, b, n).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from .model import P_LOGA, P_RHO_S
from .settings import TUNING, RefineSettings


class LobePrior(NamedTuple):
    """N texels' basis-material lobes as priors (``refine_toward``): alphas ``(N, 2)``, rho_s ``(N, 3)``
    and their 1-sigma spreads, of log alpha ``(N,)`` and of rho_s ``(N,)`` (linear units)."""

    alpha: Tensor
    rho_s: Tensor
    log_alpha_sigma: Tensor
    rho_s_sigma: Tensor


class Prior(NamedTuple):
    """Gaussian pulls per texel: the normal toward ``n_prior (N, 3)`` (the start's or the mesh's,
    ``normal_prior``; geometric frame, weight ``n_w = 1 / sigma^2`` in rad^-2), log alphas toward
    ``la0 (N, 2)`` (``la_w (N,)``) and rho_s toward ``rs0 (N, 3)`` (``rs_w (N,)``; 0 = none): the
    start's, or a basis material's. ``tie_w (N,)``: a pull of log alpha_x to log alpha_y
    (``TUNING.solver.isotropic_tie``: an isotropic lobe; 0 = none). ``tint_w``: rho_s's channels to their mean
    (``RefineSettings.rho_s_tint_sigma^-2``, relative to the mean: ``tint_scale``)."""

    n_prior: Tensor
    n_w: float
    la0: Tensor
    la_w: Tensor
    rs0: Tensor
    rs_w: Tensor
    tie_w: Tensor
    tint_w: float

    def rows(self, idx: Tensor) -> Prior:
        """The prior of the texels ``idx`` alone."""
        return Prior(
            self.n_prior[idx],
            self.n_w,
            self.la0[idx],
            self.la_w[idx],
            self.rs0[idx],
            self.rs_w[idx],
            self.tie_w[idx],
            self.tint_w,
        )

    def tied(self, isotropic: Tensor) -> Prior:
        """The same pulls with the lobes of the texels ``isotropic (N,)`` (bool) held isotropic."""
        return self._replace(tie_w=torch.where(isotropic, TUNING.solver.isotropic_tie, 0.0).to(self.la_w.dtype))

    @classmethod
    def weak(cls, frame: Tensor, p: Tensor, settings: RefineSettings) -> Prior:
        """The weak pulls (``RefineSettings``) to the start ``frame``, ``p`` — the normal to the
        mesh's instead with ``settings.normal_prior_at_mesh`` —; none on rho_s."""
        N = p.shape[0]
        return cls(
            normal_prior(frame, settings),
            math.radians(settings.normal_prior_deg) ** -2,
            p[:, P_LOGA].clone(),
            torch.full((N,), settings.log_alpha_prior_sigma**-2, dtype=p.dtype),
            torch.zeros(N, 3, dtype=p.dtype),
            torch.zeros(N, dtype=p.dtype),
            torch.zeros(N, dtype=p.dtype),
            settings.rho_s_tint_sigma**-2,
        )


def tint_scale(rho_s: Tensor) -> Tensor:
    """1 / (mean channel^2 + TUNING.solver.tint_floor^2) ``(N,)`` of ``rho_s (N, 3)``: the tint pull is relative."""
    return 1.0 / (rho_s.mean(1) ** 2 + TUNING.solver.tint_floor**2)


def prior_cost(p: Tensor, prior: Prior) -> Tensor:
    """The alpha and rho_s pulls' cost per texel at ``p (N, 11)``."""
    la = 0.5 * prior.la_w * ((p[:, P_LOGA] - prior.la0) ** 2).sum(1)
    la = la + 0.5 * prior.tie_w * (p[:, 3] - p[:, 4]) ** 2
    rs = p[:, P_RHO_S]
    tint = 0.5 * prior.tint_w * tint_scale(rs) * ((rs - rs.mean(1, keepdim=True)) ** 2).sum(1)
    return la + tint + 0.5 * prior.rs_w * ((rs - prior.rs0) ** 2).sum(1)


def normal_prior(frame: Tensor, settings: RefineSettings) -> Tensor:
    """Where the normal's weak pull centres ``(N, 3)`` (geometric frame): the normal of the start
    ``frame (N, 3, 3)``, or the mesh's (+z) with ``settings.normal_prior_at_mesh``."""
    if not settings.normal_prior_at_mesh:
        return frame[:, 2].clone()
    out = torch.zeros_like(frame[:, 2])
    out[:, 2] = 1
    return out


def prior_normal_in(frame: Tensor, n_prior: Tensor) -> Tensor:
    """The prior's normal ``n_prior (N, 3)`` (geometric frame) in the shading frame ``frame (N, 3,
    3)`` (rows t, b, n; a round's start turned by ``fold``) ``(N, 3)``."""
    return (frame @ n_prior[:, :, None])[..., 0]
