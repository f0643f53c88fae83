"""The paper's fitter, kept as the benchmark baseline: per-texel scipy L-BFGS-B.

Same objective as the batched fitter's polish and metric: mean over all 6144 lights of
(log(1 + model) - log(1 + m))^2, parameters (normal polar/azimuth angles in the lumitexel frame,
tangent angle, log alpha_x, log alpha_y, log rho_s) with alphas bounded to [0.006, 0.5];
float64, gradients by autograd. Started from the lobe's brightest light (n = its half vector),
isotropic alpha 0.1, rho_s matched to the peak.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.optimize import minimize

from ..physics.brdf import ALPHA_MAX, ALPHA_MIN
from ..physics.frame import any_tangent, cross
from ..physics.lumitexel import SPECULAR_RES, specular_lumitexel
from .flags import TexelFlag
from .geometry import GeometryFit, canonical_lobe, light_table


def _frame_from_params(x: torch.Tensor):
    theta, phi, psi = x[0], x[1], x[2]
    n = torch.stack([torch.sin(theta) * torch.cos(phi), torch.sin(theta) * torch.sin(phi), torch.cos(theta)])
    t0 = any_tangent(n)
    b0 = cross(n, t0)
    t = torch.cos(psi) * t0 + torch.sin(psi) * b0
    return n, t, torch.exp(x[3]), torch.exp(x[4]), torch.exp(x[5])


def _objective(x_np: np.ndarray, target: torch.Tensor) -> tuple[float, np.ndarray]:
    x = torch.tensor(x_np, dtype=torch.float64, requires_grad=True)
    n, t, ax, ay, rho = _frame_from_params(x)
    model = specular_lumitexel(n, t, rho[None], ax, ay, SPECULAR_RES)[..., 0]
    loss = ((torch.log1p(model) - target) ** 2).mean()
    loss.backward()
    assert x.grad is not None  # backward() filled it
    return loss.item(), x.grad.numpy()


def fit_geometry_lbfgsb(specular: torch.Tensor, max_iter: int = 200) -> GeometryFit:
    """Fit texels one at a time; ``specular (N, 6144)``. Returns the same fields as the batched fit."""
    tab = light_table(SPECULAR_RES, "cpu", torch.float64)
    N = len(specular)
    out: dict[str, list] = {k: [] for k in ("n", "t", "ax", "ay", "rho", "flags")}
    bounds = [
        (0.0, math.radians(89.0)),
        (None, None),
        (None, None),
        (math.log(ALPHA_MIN), math.log(ALPHA_MAX)),
        (math.log(ALPHA_MIN), math.log(ALPHA_MAX)),
        (math.log(1e-4), math.log(1e3)),
    ]
    for i in range(N):
        m = specular[i].double()
        flag = 0
        if not torch.isfinite(m).all():
            flag |= TexelFlag.NONFINITE
            m = torch.where(torch.isfinite(m), m, torch.zeros_like(m))
        m = m.clamp_min(0)
        if float(m.max()) <= 1e-8:
            flag |= TexelFlag.ZERO
        target = torch.log1p(m)
        h = tab["h"][int(m.argmax())]
        theta0 = float(torch.acos(h[2].clamp(-1, 1)))
        phi0 = float(torch.atan2(h[1], h[0]))
        x0 = np.array([min(theta0, math.radians(85)), phi0, 0.0, math.log(0.1), math.log(0.1), 0.0])
        n0, t0 = _frame_from_params(torch.tensor(x0))[:2]
        peak1 = float(
            specular_lumitexel(
                n0,
                t0,
                torch.ones(1, dtype=torch.float64),
                torch.tensor(0.1, dtype=torch.float64),
                torch.tensor(0.1, dtype=torch.float64),
            ).max()
        )
        x0[5] = math.log(max(float(m.max()), 1e-6) / max(peak1, 1e-12))
        x0[5] = min(max(x0[5], bounds[5][0]), bounds[5][1])
        if flag == 0:
            res = minimize(
                _objective,
                x0,
                args=(target,),
                jac=True,
                method="L-BFGS-B",
                bounds=bounds,
                options={"maxiter": max_iter},
            )
            x = res.x
            if not np.isfinite(res.fun):
                flag |= TexelFlag.NO_LOBE
        else:
            x = x0
        n, t, ax, ay, rho = _frame_from_params(torch.tensor(x))
        for k, v in zip(("n", "t", "ax", "ay", "rho", "flags"), (n, t, ax, ay, rho, flag)):
            out[k].append(v)
    if N == 0:
        e = torch.zeros(0)
        return GeometryFit(torch.zeros(0, 3), torch.zeros(0, 3), e, e, e, torch.zeros(0, dtype=torch.int64), None)
    n, t = torch.stack(out["n"]).float(), torch.stack(out["t"]).float()
    ax, ay = torch.stack(out["ax"]).float(), torch.stack(out["ay"]).float()
    n, t, ax, ay = canonical_lobe(n, t, ax, ay)
    return GeometryFit(n, t, ax, ay, torch.stack(out["rho"]).float(), torch.tensor(out["flags"]), None)
