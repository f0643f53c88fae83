"""Exact specular lumitexels of random GGX lobes for the fitting tests."""

import torch

from ntp_engine.learn.synthetic import _random_orthogonal, sample_brdfs
from ntp_engine.physics.frame import safe_normalize
from ntp_engine.physics.lumitexel import specular_lumitexel


def exact_lobes(n_tex: int = 256, seed: int = 0, tilt: float = 0.15):
    """(lumitexels (N, 6144), n, t, alpha_x, alpha_y, grey rho_s) of random lobes tilted ~``tilt``."""
    g = torch.Generator().manual_seed(seed)
    p = sample_brdfs(n_tex, g)
    z = torch.zeros(n_tex, 3)
    z[:, 2] = 1
    n = safe_normalize(z + _random_orthogonal(z, g) * (tilt * torch.randn(n_tex, 1, generator=g)))
    t = _random_orthogonal(n, g)
    rho = p["rho_s"].mean(-1)
    m = specular_lumitexel(n, t, rho[:, None], p["alpha_x"], p["alpha_y"])[..., 0]
    return m, n, t, p["alpha_x"], p["alpha_y"], rho


def angle_deg(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Angle between unit vectors ``(..., 3)``, degrees."""
    return torch.rad2deg(torch.acos((a * b).sum(-1).clamp(-1, 1)))
