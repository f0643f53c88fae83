"""Compile the engine's numba loops into their cache ahead of the first run (``make setup`` runs
``python -m ntp_engine.pipeline.precompile``), as a C extension is built at install time.

Every loop (``fit.lobe_loop``, ``physics.pattern_sums``, ``refine.pixel_bases``, ``refine.gauss_newton``)
is compiled on its first call and cached beside its source (``cache=True``); on a fresh clone that
first call was in the user's first run — ~25 s of the demo's 5 minutes on 2 cores (docs/architecture.md). Here
each is called once on a few synthetic traces through the same public functions the pipeline calls,
which hand the loops arrays of fixed dtypes and layouts, so the pipeline's calls hit the cache. A
loop this misses still compiles on its first call in a run: only slower, never wrong.
"""

from __future__ import annotations

import time

import torch

from ..fit.albedo import highlights_and_albedo
from ..fit.geometry import fit_geometry
from ..learn.synthetic import SyntheticConfig, sample_batch
from ..physics.lumitexel import diffuse_lumitexel, specular_lumitexel
from ..refine.model import Observations, Start
from ..refine.policy import refine
from ..refine.settings import RefineSettings
from ..scanner.device_file import load_scanner

TEXELS, VIEWS = 8, 6


def precompile() -> float:
    """Run each compiled loop once (see the module docstring); returns the seconds it took."""
    t0 = time.perf_counter()
    scanner = load_scanner()
    gen = torch.Generator().manual_seed(0)
    b = sample_batch(scanner, TEXELS, gen, SyntheticConfig(views_min=VIEWS, views_max=VIEWS))
    p = b.params
    # the true lobes' lumitexels, so the lobe fit runs its whole loop (fit.lobe_loop)
    grey = torch.ones(TEXELS, 1)
    specular = specular_lumitexel(p["n_local"], p["t_local"], grey, p["alpha_x"], p["alpha_y"])[..., 0]
    geometry = fit_geometry(specular, diffuse_lumitexel(p["n_local"], grey)[..., 0])
    pixels = 0.2 + 0.6 * torch.rand(TEXELS, VIEWS, 3, generator=gen)
    highlights_and_albedo(scanner, pixels, b.position, b.normal_geo, b.tangent_geo, b.length_mask, geometry)
    entries = torch.cat([pixels, b.position, b.normal_geo, b.tangent_geo], -1)
    start = Start(p["n_local"], p["t_local"], torch.full((TEXELS, 2), 0.1), p["rho_d"], torch.ones(TEXELS, 3))
    refine(
        Observations(scanner, entries, b.length_mask),
        start,
        torch.ones(TEXELS, dtype=torch.bool),
        RefineSettings(rounds=2),
    )
    return time.perf_counter() - t0


if __name__ == "__main__":
    print(f"ntp: the engine's compiled loops are cached ({precompile():.0f} s)")
