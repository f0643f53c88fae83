"""``make setup`` compiles every numba loop the pipeline calls, with the signatures its calls use."""

import torch

from ntp_engine.fit import lobe_loop
from ntp_engine.learn.synthetic import SyntheticConfig, sample_batch
from ntp_engine.physics import pattern_sums
from ntp_engine.pipeline.precompile import precompile
from ntp_engine.refine import pixel_bases
from ntp_engine.refine.model import Observations, Start
from ntp_engine.refine.policy import refine
from ntp_engine.refine.settings import RefineSettings
from ntp_engine.scanner.device_file import load_scanner

LOOPS = [
    lobe_loop.fit_lobes,
    pattern_sums._pattern_sums_loop,
    pixel_bases._diffuse_loop,
    pixel_bases._specular_loop,
    pixel_bases._lobe_loop,
    pixel_bases._select_loop,
    pixel_bases._directions_loop,
]


def test_every_loop_is_compiled_and_a_refinement_of_other_traces_needs_no_other_signature():
    precompile()
    compiled = [len(loop.signatures) for loop in LOOPS]
    assert all(compiled), compiled
    dev = load_scanner()
    b = sample_batch(dev, 5, torch.Generator().manual_seed(3), SyntheticConfig(views_min=9, views_max=12))
    p = b.params
    entries = torch.cat([torch.rand(5, b.length_mask.shape[1], 3), b.position, b.normal_geo, b.tangent_geo], -1)
    start = Start(p["n_local"], p["t_local"], torch.full((5, 2), 0.2), p["rho_d"], p["rho_s"])
    refine(Observations(dev, entries, b.length_mask), start, torch.ones(5, dtype=torch.bool), RefineSettings(rounds=1))
    assert [len(loop.signatures) for loop in LOOPS] == compiled
