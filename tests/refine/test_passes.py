import numpy as np
import torch
from refine.test_inputs import _square, _square_in_two_views

from ntp_engine.fit.flags import TexelFlag
from ntp_engine.fit.texel_fit import TexelFit
from ntp_engine.learn.ragged import RaggedTraces
from ntp_engine.refine import passes as passes_module
from ntp_engine.refine.model import Observations
from ntp_engine.scanner.device_file import load_scanner


def test_the_edge_pass_starts_from_the_first_pass_and_seeks_a_lobe_only_where_it_kept_one(monkeypatch):
    """``refine_fit`` on a flat square of two albedos (0.3 | 0.7) seen in two views: the texels next
    to the edge are refined again with the blend as noise, from the first pass's answers in
    ``edge_rounds`` without the multi-start, the pulls centred on the start; those whose first pass
    kept no lobe seek none there (their warm start says no highlight); their answers have none."""

    from ntp_engine.refine.settings import RefineSettings

    tx, traces = _square_in_two_views(0.8, (0.02, 0.05))  # farther: a pixel spans ~a texel
    dev = load_scanner()
    N = len(tx)
    start = {"n_loc": np.tile([0.0, 0, 1], (N, 1)), "t_loc": np.tile([1.0, 0, 0], (N, 1))}
    start |= {"alpha": np.full((N, 2), 0.2), "rho_d": np.full((N, 3), 0.5), "rho_s": np.full((N, 3), 1.0)}
    start["flags"] = np.zeros(N, np.int64)
    start = TexelFit.from_arrays(start)
    calls = []
    real = passes_module._refine_texels

    def spy(scanner, traces, fit, start, todo, settings, progress, texels, support, name, centre=None):
        calls.append((name, todo.numpy().copy(), start.copy(), settings, centre))
        calls[-1] += (fit.copy(),)
        real(scanner, traces, fit, start, todo, settings, progress, texels, support, name, centre)

    monkeypatch.setattr(passes_module, "_refine_texels", spy)
    out = passes_module.refine_fit(dev, traces, start, RefineSettings(materials=False), texels=tx)
    assert [c[0] for c in calls] == ["refine", "albedo edges"]
    _, edges, warm, settings, centre, first = calls[1]
    assert 0 < len(edges) < N
    assert settings.rounds == passes_module.TUNING.inputs.edge_rounds and not settings.starts
    for key in ("n_loc", "t_loc", "alpha", "rho_d", "rho_s"):
        np.testing.assert_array_equal(getattr(warm, key), getattr(first, key))  # the first pass's answers
        np.testing.assert_array_equal(getattr(centre, key), getattr(start, key))  # the pulls: the start's
    lobeless = first.flags[edges] & TexelFlag.SPECULAR_UNCONSTRAINED != 0
    assert lobeless.any()
    np.testing.assert_array_equal(warm.flags[edges] & TexelFlag.NO_HIGHLIGHT != 0, lobeless)
    assert (out.rho_s[edges[lobeless]] == 0).all()


def test_every_pass_of_the_refinement_counts_its_texels_to_the_end(tmp_path):
    """``refine_fit`` reports each pass, the entries it reads and the albedo blend among them, as a
    progress stage that ends with every texel counted: a run of minutes shows where it is."""
    import json

    from ntp_engine.io.progress import Progress
    from ntp_engine.refine.settings import RefineSettings

    tx, traces = _square_in_two_views(0.8, (0.02, 0.05))
    N = len(tx)
    start = {"n_loc": np.tile([0.0, 0, 1], (N, 1)), "t_loc": np.tile([1.0, 0, 0], (N, 1))}
    start |= {"alpha": np.full((N, 2), 0.2), "rho_d": np.full((N, 3), 0.5), "rho_s": np.full((N, 3), 1.0)}
    start["flags"] = np.zeros(N, np.int64)
    log = tmp_path / "progress.jsonl"
    passes_module.refine_fit(
        load_scanner(), traces, TexelFit.from_arrays(start), RefineSettings(), Progress(json_path=log), texels=tx
    )
    last: dict[str, dict] = {}
    for line in log.read_text().splitlines():
        row = json.loads(line)
        last[row["stage"]] = row
    for stage in ("entries read", "refine", "albedo blend", "albedo edges"):
        assert stage in last, stage
    for row in last.values():
        assert row["done"] == row["total"], row
    assert last["entries read"]["total"] == last["refine"]["total"] == N
    assert last["albedo blend"]["total"] == N


def test_normals_are_fused_within_each_material_with_tangents_kept_orthogonal():
    from ntp_engine.io.texels import Texels
    from ntp_engine.refine.passes import fuse_normals

    n = 24
    g = np.stack(np.meshgrid(np.arange(n), np.arange(n), indexing="ij"), -1).reshape(-1, 2)
    N = len(g)
    position = np.concatenate([g * 0.001, np.zeros((N, 1))], 1)
    # geometric frames turned about +z texel by texel: the local normals differ from object space
    phi = np.linspace(0.0, 2.0, N)
    tangent = np.stack([np.cos(phi), np.sin(phi), np.zeros(N)], 1)
    texels = Texels((n, n), g[:, 0], g[:, 1], np.zeros(N, int), np.full((N, 3), 1 / 3), position,
                    np.tile([0.0, 0.0, 1.0], (N, 1)), tangent)  # fmt: skip
    rng = np.random.default_rng(0)
    n_loc = np.concatenate([rng.normal(0.0, 0.02, (N, 2)), np.ones((N, 1))], 1)
    n_loc /= np.linalg.norm(n_loc, axis=1, keepdims=True)
    material = np.where(g[:, 0] < n // 2, 0, -1)  # two groups, fused apart
    n_loc[material == -1] = [0.0, 0.0, 1.0]
    t_loc = np.array([1.0, 0.0, 0.0]) - n_loc[:, :1] * n_loc
    t_loc /= np.linalg.norm(t_loc, axis=1, keepdims=True)
    fit = TexelFit.defaults(N)
    fit.n_loc, fit.t_loc, fit.material = n_loc.copy(), t_loc, material
    fit.std = np.tile([np.degrees(0.02 * np.sqrt(2)), 5.0, 0.1, 0.1], (N, 1))
    fit.std[0, 0] = np.nan  # no normal std: kept
    fuse_normals(fit, texels, np.arange(N))
    tilt_before = np.degrees(np.arccos(n_loc[material == 0, 2]))
    tilt_after = np.degrees(np.arccos(np.clip(fit.n_loc[material == 0, 2], -1, 1)))
    assert np.median(tilt_after) < 0.5 * np.median(tilt_before)
    np.testing.assert_allclose(fit.n_loc[material == -1], n_loc[material == -1], atol=1e-12)  # not the other's
    np.testing.assert_allclose(fit.n_loc[0], n_loc[0])
    np.testing.assert_allclose((fit.n_loc * fit.t_loc).sum(1), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(fit.t_loc, axis=1), 1.0)
    assert np.nanmedian(fit.std[material == 0, 0]) < 0.5 * np.degrees(0.02 * np.sqrt(2))


def test_the_albedos_next_to_an_edge_come_back_sharper_from_the_entries_pixel_samples():
    """A flat square 0.2 | 0.8 seen from 8 poses a fraction of a pixel apart (a pixel spans ~a
    texel), each entry's pixel the diffuse light times the albedos its four taps see (as the camera
    samples them): each texel's own answer is blurred next to the edge; ``sharpen_albedos`` on the
    texels beside it brings them back more than half way, holds the rest, and never gives NaN."""
    from ntp_engine.refine.albedo_map import tap_texels
    from ntp_engine.refine.footprint import sample_points
    from ntp_engine.refine.model import Start, predicted_light
    from ntp_engine.refine.settings import RefineSettings

    tx = _square()
    N, V = len(tx), 8
    truth = np.where(tx.col[:, None] < 16, 0.2, 0.8) * np.ones(3)
    R = np.diag([1.0, -1.0, -1.0])
    rows = []
    for k in range(V):
        x = tx.position @ R.T + [-0.008 + 1.3e-4 * k, 0.008 + 0.7e-4 * k, 0.8]
        n, t = np.tile(R @ [0, 0, 1.0], (N, 1)), np.tile(R @ [1.0, 0, 0], (N, 1))
        rows.append(np.concatenate([np.ones((N, 3)), x, n, t], 1))
    entries = torch.as_tensor(np.stack(rows, 1), dtype=torch.float32)
    mask = torch.ones(N, V, dtype=torch.bool)
    dev = load_scanner()
    fit = {"n_loc": np.tile([0.0, 0, 1], (N, 1)), "t_loc": np.tile([1.0, 0, 0], (N, 1))}
    fit |= {"alpha": np.full((N, 2), 0.2), "rho_d": truth.copy(), "rho_s": np.zeros((N, 3))}
    fit["flags"] = np.zeros(N, np.int64)
    fit = TexelFit.from_arrays(fit)
    diffuse, _, _ = predicted_light(Observations(dev, entries, mask), Start.from_fit(fit, np.arange(N)))
    delta, weight = sample_points(dev, entries, mask)
    index = np.full(tx.shape, -1, np.int64)
    index[tx.row, tx.col] = np.arange(N)
    taps, w = tap_texels(delta.numpy(), weight.numpy(), tx.uv, tx.uv_per_metre, index)
    y = diffuse.numpy() * (w[..., None] * truth[taps]).sum(2)
    entries[..., :3] = torch.as_tensor(y, dtype=torch.float32)
    d = diffuse.numpy()
    fit.rho_d = (d * y).sum(1) / (d * d).sum(1)  # each texel's own answer
    traces = RaggedTraces(entries.reshape(-1, 12), torch.arange(0, V * N + 1, V))
    beside = np.nonzero(np.abs(tx.col + 0.5 - 16) < 3)[0]
    own = fit.rho_d.copy()
    assert np.abs(own[beside] - truth[beside]).max() > 0.02  # blurred
    passes_module.sharpen_albedos(dev, traces, fit, torch.as_tensor(beside), RefineSettings(), tx)
    out = fit.rho_d
    assert np.isfinite(out).all()
    np.testing.assert_array_equal(np.delete(out, beside, 0), np.delete(own, beside, 0))
    before, after = (np.sqrt(((a[beside] - truth[beside]) ** 2).mean()) for a in (own, out))
    assert after < 0.5 * before


def test_refine_fit_sharpens_the_albedos_of_the_edge_pass_texels_only_when_asked(monkeypatch):
    """``refine_fit`` solves the albedo map (``sharpen_albedos``) over texels the edge pass refined
    (those that may blend ``min_blend`` or more), after every other step;
    ``RefineSettings(albedo_map=False)`` leaves it out."""
    from ntp_engine.refine.settings import RefineSettings

    tx, traces = _square_in_two_views(0.8, (0.05, 0.3))
    dev = load_scanner()
    N = len(tx)
    start = {"n_loc": np.tile([0.0, 0, 1], (N, 1)), "t_loc": np.tile([1.0, 0, 0], (N, 1))}
    start |= {"alpha": np.full((N, 2), 0.2), "rho_d": np.full((N, 3), 0.5), "rho_s": np.full((N, 3), 1.0)}
    start["flags"] = np.zeros(N, np.int64)
    start = TexelFit.from_arrays(start)
    passes, sharpened = [], []
    real_pass, real_sharpen = passes_module._refine_texels, passes_module.sharpen_albedos

    def spy_pass(scanner, traces, fit, start, todo, settings, progress, texels, support, name, centre=None):
        passes.append((name, todo.numpy().copy()))
        real_pass(scanner, traces, fit, start, todo, settings, progress, texels, support, name, centre)

    def spy_sharpen(scanner, traces, fit, idx, *args, **kwargs):
        sharpened.append((idx.numpy().copy(), fit.n_loc.copy()))
        real_sharpen(scanner, traces, fit, idx, *args, **kwargs)

    monkeypatch.setattr(passes_module, "_refine_texels", spy_pass)
    monkeypatch.setattr(passes_module, "sharpen_albedos", spy_sharpen)
    out = passes_module.refine_fit(dev, traces, start, RefineSettings(materials=False), texels=tx)
    assert [p[0] for p in passes] == ["refine", "albedo edges"] and len(sharpened) == 1
    assert 0 < len(sharpened[0][0]) and np.isin(sharpened[0][0], passes[1][1]).all()
    np.testing.assert_array_equal(sharpened[0][1], out.n_loc)  # after the normals were fused
    assert np.isfinite(out.rho_d).all()
    passes.clear()
    passes_module.refine_fit(dev, traces, start, RefineSettings(materials=False, albedo_map=False), texels=tx)
    assert len(sharpened) == 1
    # without the edge pass the blend still picks the albedo map's texels, which are solved jointly
    passes.clear()
    lean = passes_module.refine_fit(dev, traces, start, RefineSettings(materials=False, edge_pass=False), texels=tx)
    assert [p[0] for p in passes] == ["refine"] and len(sharpened) == 2
    np.testing.assert_array_equal(sharpened[1][0], sharpened[0][0])
    assert np.isfinite(lean.rho_d).all()
