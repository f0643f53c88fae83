import numpy as np
import torch

from ntp_engine.fit.geometry import FALLBACK_ALPHA
from ntp_engine.io.tuned import retuned
from ntp_engine.learn import models
from ntp_engine.learn.ragged import RaggedTraces
from ntp_engine.learn.synthetic import SyntheticConfig, sample_batch
from ntp_engine.pipeline import fit_traces as fit_traces_module
from ntp_engine.pipeline.fit_traces import fit_blocks, fit_traces
from ntp_engine.scanner.device_file import load_scanner


def test_every_trace_gets_finite_parameters_in_range_and_empty_ones_the_defaults():
    scanner = load_scanner()
    net, _ = models.load(None, scanner)
    gen = torch.Generator().manual_seed(3)
    b = sample_batch(scanner, 24, gen, SyntheticConfig(), views=32)
    with torch.no_grad():
        pixel, valid = net.measure_batch(b, gen)
    entries = torch.cat([pixel, b.position, b.normal_geo, b.tangent_geo], -1)
    valid[:4] = False  # four traces no photo saw
    out = fit_traces(net, scanner, RaggedTraces.from_padded(entries, valid), pixel_scale=1.0, batch=8)
    assert all(np.isfinite(v).all() for v in out.arrays().values())
    np.testing.assert_allclose(out.n_loc[:4], [[0, 0, 1]] * 4)
    np.testing.assert_allclose(out.alpha[:4], FALLBACK_ALPHA)
    seen = out.alpha[4:]
    assert ((seen >= 0.006) & (seen <= 0.5)).all() and (seen[:, 0] >= seen[:, 1]).all()
    assert ((out.rho_d >= 0) & (out.rho_d <= 1)).all() and ((out.rho_s >= 0) & (out.rho_s <= 10)).all()
    normal_err = np.degrees(np.arccos(np.clip((out.n_loc[4:] * b.params["n_local"][4:].numpy()).sum(1), -1, 1)))
    assert np.median(normal_err) < 10  # the network + fit recover the shading normal roughly


def test_blocks_give_the_whole_tables_answer_from_unscaled_pixels(monkeypatch):
    """``fit_blocks`` over blocks of 5 traces, pixels as captured, equals ``fit_traces`` on the
    whole table with its pixels scaled; the table itself is left as it was."""
    scanner = load_scanner()
    net, _ = models.load(None, scanner)
    gen = torch.Generator().manual_seed(4)
    b = sample_batch(scanner, 13, gen, SyntheticConfig(), views=16)
    with torch.no_grad():
        pixel, valid = net.measure_batch(b, gen)
    valid[6] = False
    scale = 2.0
    entries = torch.cat([pixel / scale, b.position, b.normal_geo, b.tangent_geo], -1)
    captured = RaggedTraces.from_padded(entries, valid)
    before = captured.entries.clone()
    scaled = RaggedTraces(captured.entries.clone(), captured.offsets)
    scaled.entries[:, :3] *= scale
    whole = fit_traces(net, scanner, scaled, scale)
    monkeypatch.setattr(fit_traces_module, "TUNING", retuned(fit_traces_module.TUNING, "fit", fit_block=5))
    blocks = fit_blocks(net, scanner, captured, scale)
    assert torch.equal(captured.entries, before)
    assert set(blocks.arrays()) == set(whole.arrays())
    for k, v in whole.arrays().items():  # float32 network batches of other sizes: equal to rounding
        np.testing.assert_allclose(blocks.arrays()[k], v, rtol=1e-3, atol=1e-3, err_msg=k)
