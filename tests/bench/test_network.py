import pytest


@pytest.mark.slow  # measured over 5 s on 2 cores
def test_network_benchmark_reads_shipped_models_and_reports_the_keys(tmp_path):
    import json

    from ntp_engine.bench import network as bench_network

    out = tmp_path / "bn.json"
    bench_network.run(quick=True, json_path=out, batches=2, rate_traces=256)
    r = json.loads(out.read_text())
    by = r["val_loss_by_pattern"]
    assert set(by) == {"optimized", "full_on", "point"}
    assert set(r["val_loss_by_test_views"]) == {"8", "16", "32", "64", "128"}
    assert r["traces_per_s"] > 0 and all(v > 0 for v in by.values())
    for k in ("optimized", "point"):  # paired over the same batches: the mean difference is the difference
        d = r["val_loss_minus_full_on"][k]
        assert d["mean"] == pytest.approx(by[k] - by["full_on"], abs=1e-9) and d["standard_error"] >= 0
    assert all(0 <= v <= 1 for v in r["valid_views_by_pattern"].values())


@pytest.mark.slow  # measured over 5 s on 2 cores
def test_bench_network_trains_the_pattern_comparison_from_shared_halfway_networks():
    """The Fig. 14 protocol without --quick: optimised and full-on continue the same half-way
    full-on network; only the optimised one's pattern moves."""
    from ntp_engine.bench import network as bench_network

    nets = bench_network._comparison_models(False, 2)
    assert set(nets) == {"optimized", "full_on", "point"}
    opt, full, point = (nets[k].pattern().detach() for k in ("optimized", "full_on", "point"))
    assert (full > 0.99).all() and (point > 0.99).all(1).sum() == 1
    assert 0.4 < float(opt.mean()) < 0.6 and float(opt.std()) > 0  # started at 0.5 and learned
    shared = [k for k in nets["full_on"].state_dict() if k.startswith("encoder")]
    assert shared and all(
        nets["optimized"].state_dict()[k].shape == nets["full_on"].state_dict()[k].shape for k in shared
    )
