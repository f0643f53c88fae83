import torch

from ntp_engine.learn import network
from ntp_engine.learn.inference import RaggedTraces, predict, predict_all
from ntp_engine.learn.network import NetworkConfig, TraceNet
from ntp_engine.scanner.device_file import load_scanner


def _traces(n=9, seed=0):
    gen = torch.Generator().manual_seed(seed)
    lengths = torch.randint(0, 12, (n,), generator=gen)
    lengths[0] = 0  # an empty trace
    offsets = torch.zeros(n + 1, dtype=torch.int64)
    offsets[1:] = torch.cumsum(lengths, 0)
    entries = torch.rand(int(offsets[-1]), 12, generator=gen)
    return RaggedTraces(entries, offsets)


def test_ragged_prediction_matches_padded_forward_in_any_batching():
    torch.manual_seed(0)
    net = TraceNet(NetworkConfig(preset="small"), load_scanner()).eval()
    tr = _traces()
    d_all, s_all = predict_all(net, tr, max_entries=1 << 12)
    d_small, s_small = predict_all(net, tr, max_entries=13)  # many tiny batches
    torch.testing.assert_close(d_all, d_small)
    torch.testing.assert_close(s_all, s_small)
    for k in (1, 4):
        a, b = int(tr.offsets[k]), int(tr.offsets[k + 1])
        raw = tr.entries[a:b][None]
        x = net.entries(raw[..., :3], raw[..., 3:6], raw[..., 6:9], raw[..., 9:])
        with torch.no_grad():
            d, s = net(x, torch.ones(1, b - a, dtype=torch.bool))
        torch.testing.assert_close(d_all[k], d[0].clamp_min(0))
        torch.testing.assert_close(s_all[k], torch.expm1(s[0].clamp_min(0)))
    assert (s_all >= 0).all() and torch.isfinite(d_all).all()
    seen = torch.cat([idx for idx, _, _ in predict(net, tr, max_entries=20)])
    assert sorted(seen.tolist()) == list(range(tr.num_traces))


def test_the_encoder_pooled_in_chunks_is_the_encoder_pooled_at_once(monkeypatch):
    # chunks that split traces (and an empty one) pool to the same features
    torch.manual_seed(0)
    net = TraceNet(NetworkConfig(preset="small"), load_scanner()).eval()
    tr = _traces(n=12, seed=3)
    x = net.entries(tr.entries[:, :3], tr.entries[:, 3:6], tr.entries[:, 6:9], tr.entries[:, 9:])
    with torch.no_grad():
        whole = net.forward_ragged(x, tr.offsets)
        monkeypatch.setattr(network, "ENCODER_CHUNK", 5)
        chunked = net.forward_ragged(x, tr.offsets)
        empty = net.forward_ragged(x[:0], torch.zeros(3, dtype=torch.int64))
        masked = net(x[:2].reshape(2, 1, 12), torch.zeros(2, 1, dtype=torch.bool))
    assert len(x) > 5 and (tr.lengths == 0).any()
    for a, b in zip(whole, chunked, strict=True):  # equal up to the matrix kernels' rounding by row count
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-6)
    for a, b in zip(empty, masked, strict=True):  # traces with no entry: the network's prior
        torch.testing.assert_close(a, b)


def test_a_view_cap_feeds_the_network_evenly_spread_entries():
    torch.manual_seed(0)
    net = TraceNet(NetworkConfig(preset="small"), load_scanner()).eval()
    tr = _traces(n=7, seed=3)
    cap = 4
    capped = {}
    for idx, _, s in predict(net, tr, max_entries=16, max_views=cap):
        capped.update({int(i): s[j] for j, i in enumerate(idx)})
    assert sorted(capped) == list(range(tr.num_traces)) and int(tr.lengths.max()) > cap  # the cap does something
    for k in range(tr.num_traces):
        a, n = int(tr.offsets[k]), int(tr.lengths[k])
        if n == 0:
            continue
        kept = min(n, cap)
        keep = [a + round(j * (n - 1) / max(kept - 1, 1)) for j in range(kept)]  # first and last kept
        raw = tr.entries[keep][None]
        x = net.entries(raw[..., :3], raw[..., 3:6], raw[..., 6:9], raw[..., 9:])
        with torch.no_grad():
            _, s = net(x, torch.ones(1, len(keep), dtype=torch.bool))
        torch.testing.assert_close(capped[k], torch.expm1(s[0].clamp_min(0)), msg=f"trace {k}, {n} entries")


def test_batches_hold_at_most_max_traces_even_when_traces_are_empty():
    net = TraceNet(NetworkConfig(preset="small"), load_scanner()).eval()
    empty = RaggedTraces(torch.zeros(0, 12), torch.zeros(11, dtype=torch.int64))
    sizes = [len(idx) for idx, _, _ in predict(net, empty, max_traces=4)]
    assert sizes == [4, 4, 2]
