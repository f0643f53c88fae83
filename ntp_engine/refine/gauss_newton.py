"""The refinement's robust data cost and Gauss-Newton system (``refine.solver``'s LM step) from its
pixel bases, each summed in one compiled loop (numba, parallel over texels): the cost, and the
normal equations J^T W J and J^T W r per texel over its entries and channels — without the (texels
x entries x 3 x 11) Jacobian and the dozen torch operations that built and multiplied it (~40% of
an LM step's time), or the residuals' half dozen.

Convention: parameters p ``(N, 11)`` = (omega (3), log alpha (2), rho_d RGB, rho_s RGB) as in
``refine.policy`` (omega a rotation of the shading frame at 0). Per entry v and channel c the
prediction is rho_d,c (g_c . e_z) + rho_s,c s_c, where ``diffuse (N, V, 3, 3)`` holds each
channel's diffuse basis g_c in the shading frame (d/d omega of g . n(omega) is (-g_y, g_x, 0)),
``spec (N, V, 3)`` the specular basis and ``ds (N, V, 5, 3)`` its derivatives by (omega, log alpha)
(``pixel_bases.specular_basis_and_derivatives``; both ``(0, ...)`` for a diffuse-only model). A
residual is (prediction - y) / sigma, ``inv_sigma (N, V, 3)``, counted where ``mask`` is set and,
for a ``censored`` pixel (a clipped channel), only while the prediction is below y; each is
weighted by the Cauchy IRLS weight 1 / (1 + (r / robust)^2); the cost is Cauchy's,
robust^2 / 2 log(1 + (r / robust)^2). Sums in float64.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from torch import Tensor

from ..io.jit import compiled
from ..io.thread_pools import numba_threads_as_torch
from .pixel_bases import loop_array

N_PARAMS = 11  # omega (3), log alpha (2), rho_d (3), rho_s (3)


def normal_equations(
    diffuse: Tensor,
    spec: Tensor,
    ds: Tensor,
    p: Tensor,
    y: Tensor,
    inv_sigma: Tensor,
    mask: Tensor,
    censored: Tensor,
    robust: float,
) -> tuple[Tensor, Tensor]:
    """The Gauss-Newton Hessian J^T W J ``(N, 11, 11)`` and gradient J^T W r ``(N, 11)`` (float64)
    of the robust data cost at ``p`` (module docstring)."""
    N = len(p)
    H = np.zeros((N, N_PARAMS, N_PARAMS))
    g = np.zeros((N, N_PARAMS))
    with numba_threads_as_torch():
        _normal_loop(*_loop_inputs((diffuse, spec, ds), p, y, inv_sigma, mask, censored), float(robust), H, g)
    return torch.from_numpy(H), torch.from_numpy(g)


def data_cost(
    diffuse: Tensor,
    spec: Tensor,
    p: Tensor,
    y: Tensor,
    inv_sigma: Tensor,
    mask: Tensor,
    censored: Tensor,
    robust: float,
) -> Tensor:
    """The robust data cost per texel ``(N,)`` (module docstring) at ``p (N, 11)`` of the unit-albedo
    pixel bases ``diffuse``, ``spec (N, V, 3)`` (for the normal and lobe ``p`` stands for), in
    ``y``'s dtype."""
    out = np.zeros(len(p))
    with numba_threads_as_torch():
        _cost_loop(*_loop_inputs((diffuse, spec), p, y, inv_sigma, mask, censored), float(robust), out)
    return torch.from_numpy(out).to(y.dtype)


def _loop_inputs(
    bases: tuple[Tensor, ...], p: Tensor, y: Tensor, inv_sigma: Tensor, mask: Tensor, censored: Tensor
) -> list[np.ndarray]:
    """The loops' arrays: the bases, y and sigma in y's dtype, p in float64, the masks as bools."""
    dt = y.dtype
    floats = [*(loop_array(b, dt) for b in bases), loop_array(p, torch.float64), loop_array(y, dt)]
    return [*floats, loop_array(inv_sigma, dt), loop_array(mask, torch.bool), loop_array(censored, torch.bool)]


# no fastmath in this module's loops: a solve gone non-finite must give a NaN cost (the LM rejects
# the step), which fastmath's no-NaN assumption does not promise
@compiled(parallel=True)
def _cost_loop(diffuse, spec, p, y, inv_sigma, mask, censored, robust, out):  # pragma: no cover
    """Fills ``out (N,)`` (see ``data_cost``)."""
    N, V = y.shape[0], y.shape[1]
    c2 = robust * robust
    for n in numba.prange(N):
        total = 0.0
        for v in range(V):
            for c in range(3):
                if not mask[n, v, c]:
                    continue
                pred = p[n, 5 + c] * diffuse[n, v, c] + p[n, 8 + c] * spec[n, v, c]
                if censored[n, v, c] and pred >= y[n, v, c]:
                    continue  # a clipped channel measures only a lower bound
                r = (pred - y[n, v, c]) * inv_sigma[n, v, c]
                total += 0.5 * c2 * math.log1p(r * r / c2)
        out[n] = total


@compiled(parallel=True)
def _normal_loop(diffuse, spec, ds, p, y, inv_sigma, mask, censored, robust, H, g):  # pragma: no cover
    """Fills ``H (N, 11, 11)`` and ``g (N, 11)`` (see ``normal_equations``)."""
    N, V = y.shape[0], y.shape[1]
    specular = spec.shape[0] > 0
    inv_c2 = 1.0 / (robust * robust)
    for n in numba.prange(N):
        j = np.zeros(7)  # the residual's nonzero derivatives: omega, log alpha, its rho_d, its rho_s
        col = np.zeros(7, np.int64)
        for v in range(V):
            for c in range(3):
                if not mask[n, v, c]:
                    continue
                rd, rs = p[n, 5 + c], p[n, 8 + c]
                gx, gy, gz = diffuse[n, v, c, 0], diffuse[n, v, c, 1], diffuse[n, v, c, 2]
                s = spec[n, v, c] if specular else 0.0
                pred = rd * gz + rs * s
                if censored[n, v, c] and pred >= y[n, v, c]:
                    continue  # a clipped channel measures only a lower bound
                isg = inv_sigma[n, v, c]
                r = (pred - y[n, v, c]) * isg
                w = 1.0 / (1.0 + r * r * inv_c2)
                j[0], j[1], j[2], j[3], j[4] = -rd * gy, rd * gx, 0.0, 0.0, 0.0
                if specular:
                    for k in range(5):
                        j[k] += rs * ds[n, v, k, c]
                j[5], j[6] = gz, s
                col[0], col[1], col[2], col[3], col[4], col[5], col[6] = 0, 1, 2, 3, 4, 5 + c, 8 + c
                for a in range(7):
                    ja = j[a] * isg
                    g[n, col[a]] += w * ja * r
                    for b in range(7):
                        H[n, col[a], col[b]] += w * ja * j[b] * isg
