import numpy as np
import torch

from ntp_engine.fit.geometry import FALLBACK_ALPHA
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
    assert all(np.isfinite(v).all() for v in out.values())
    np.testing.assert_allclose(out["n_loc"][:4], [[0, 0, 1]] * 4)
    np.testing.assert_allclose(out["alpha"][:4], FALLBACK_ALPHA)
    seen = out["alpha"][4:]
    assert ((seen >= 0.006) & (seen <= 0.5)).all() and (seen[:, 0] >= seen[:, 1]).all()
    assert ((out["rho_d"] >= 0) & (out["rho_d"] <= 1)).all() and ((out["rho_s"] >= 0) & (out["rho_s"] <= 10)).all()
    normal_err = np.degrees(np.arccos(np.clip((out["n_loc"][4:] * b.params["n_local"][4:].numpy()).sum(1), -1, 1)))
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
    monkeypatch.setattr(fit_traces_module, "FIT_BLOCK", 5)
    blocks = fit_blocks(net, scanner, captured, scale)
    assert torch.equal(captured.entries, before)
    assert set(blocks) == set(whole)
    for k in whole:  # float32 network batches of other sizes: equal to rounding
        np.testing.assert_allclose(blocks[k], whole[k], rtol=1e-3, atol=1e-3, err_msg=k)


def test_refine_inputs_read_marginal_entries_only_where_too_few_others_are_left():
    """A texel with at least ``MIN_CLEAR_ENTRIES`` clear entries — neither shadowed by its mesh
    (over ``MAX_SHADOWED_DRIVE`` of the drive hidden) nor grazing (wo . n^ <= ``MIN_COS_VIEW``) —
    is refined on those alone; one with fewer reads its marginal entries too, with their masks,
    and is flagged ``marginal``."""
    from ntp_engine.fit.emitter_blocks import shadow_groups
    from ntp_engine.pipeline.fit_traces import MIN_CLEAR_ENTRIES, REFINE_VIEWS, refine_inputs

    dev = load_scanner()
    half = (1 << (len(shadow_groups(dev).points) // 2)) - 1  # half the groups hidden: shadowed
    # kinds of each trace's entries (c clear, s shadowed, g grazing): plenty clear, too few, none, no entries
    kinds = ["csg" * 13 + "c", "c" * (MIN_CLEAR_ENTRIES - 1) + "sg" * 15, "sgsgs", ""]
    table = [torch.tensor([half if k == "s" else 0 for k in t], dtype=torch.int64) for t in kinds]
    shadow = torch.cat(table)
    lengths = [len(t) for t in kinds]
    offsets = torch.tensor([0, *np.cumsum(lengths)])
    entries = torch.zeros(int(offsets[-1]), 12)
    entries[:, 0] = torch.cat([torch.arange(n, dtype=torch.float32) for n in lengths])  # entry number in its trace
    entries[:, 5] = 0.3  # the point 0.3 m in front of the camera
    tilt = torch.tensor([k == "g" for t in kinds for k in t])
    cos = torch.where(tilt, 0.2, 1.0)  # wo . n^: 0.2 grazing, else facing the camera
    entries[:, 6], entries[:, 8] = (1 - cos**2).sqrt(), -cos
    traces = RaggedTraces(entries, offsets, (shadow == 0) & ~tilt, shadow)
    N = len(kinds)
    fit = {"n_loc": np.tile([0, 0, 1.0], (N, 1)), "t_loc": np.tile([1.0, 0, 0], (N, 1)), "alpha": np.full((N, 2), 0.1)}
    fit |= {"rho_d": np.full((N, 3), 0.5), "rho_s": np.zeros((N, 3)), "flags": np.zeros(N, np.int64)}
    inp = refine_inputs(dev, traces, torch.arange(N), fit)
    ent, mask, masks, marginal = inp.entries, inp.mask, inp.shadow, inp.marginal
    assert inp.support is None  # none asked for
    clear = [{k for k, c in enumerate(t) if c == "c"} for t in kinds]
    few = [len(c) < MIN_CLEAR_ENTRIES for c in clear]
    assert marginal.tolist() == [few[0], few[1], True, False]
    for i, n in enumerate(lengths):
        got = ent[i, mask[i], 0].long()
        usable = set(range(n)) if few[i] else clear[i]
        assert len(got) == min(len(usable), REFINE_VIEWS) and set(got.tolist()) <= usable
        assert torch.equal(masks[i, mask[i]], table[i][got])
    assert not few[0] and few[1] and mask[2].sum() == 5  # both cases are there


def _lobe_traces(n: int, v: int, alpha, rho_d: float, rho_s: float, seed: int):
    """``n`` synthetic traces of ``v`` entries (1% noise, 8-bit) of one material, ``alpha`` (alpha_x,
    alpha_y) or ``(n, 2)`` one per texel, alpha_x along each texel's true tangent, and a first-pass
    answer that knows the frames only."""
    from ntp_engine.physics.frame import cross
    from ntp_engine.physics.measurement import emitter_terms, measure_terms

    dev = load_scanner()
    cfg = SyntheticConfig(views_min=v, views_max=v, albedo_jitter=0.0, roughness_jitter=0.0, sweep_fraction=1.0)
    gen = torch.Generator().manual_seed(seed)
    b = sample_batch(dev, n, gen, cfg)
    geo = torch.stack([b.tangent_geo, cross(b.normal_geo, b.tangent_geo), b.normal_geo], -2)
    n_cam = torch.einsum("nvij,ni->nvj", geo, b.params["n_local"])
    t_cam = torch.einsum("nvij,ni->nvj", geo, b.params["t_local"])
    widths = torch.as_tensor(np.broadcast_to(np.asarray(alpha, np.float32), (n, 2)).copy())
    ax, ay = (widths[:, k : k + 1].expand(n, v) for k in range(2))
    a_l, s_l = emitter_terms(dev, b.position, n_cam, t_cam, ax, ay)
    lin = measure_terms(dev, a_l, s_l, torch.full((n, v, 3), rho_d), torch.full((n, v, 3), rho_s))
    lin = dev.exposure(dev.pattern) * lin
    y = torch.round((255 * lin * (1 + 0.01 * torch.randn(lin.shape, generator=gen))).clamp(0, 255)) / 255
    traces = RaggedTraces.from_padded(torch.cat([y, b.position, b.normal_geo, b.tangent_geo], -1), b.length_mask)
    start = {"n_loc": b.params["n_local"].double().numpy(), "t_loc": b.params["t_local"].double().numpy()}
    start |= {"alpha": np.full((n, 2), 0.15), "rho_d": np.full((n, 3), 0.1), "rho_s": np.full((n, 3), 3.0)}
    start["flags"] = np.zeros(n, np.int64)
    return dev, traces, start


def _material(alpha: tuple[float, float]):
    """One basis material of lobe width ``alpha`` (rho_d 0.1, rho_s 3)."""
    from ntp_engine.fit.materials import BasisMaterials

    one = np.ones((1, 1))
    return BasisMaterials(
        0.1 * one.repeat(3, 1), np.array([alpha]), 3 * one.repeat(3, 1), *[one[0]] * 4, 0.1 * one.repeat(3, 1)
    )


def test_a_materials_width_comes_from_its_members_traces_together():
    """A broad metal lobe (alpha 0.3, rho_d 0.05, rho_s 6) seen in 8 entries per texel: a material
    whose width is 2x off (the median of answers that landed by their start) gets the truth from
    its texels' traces together, and its rho_s; in the refinement's second pass the texels whose
    traces cannot tell their own width from the material's take it, their albedos re-solved
    (flagged ``FLAG_WIDTH_FROM_MATERIAL``)."""
    from ntp_engine.fit.refine import FLAG_SPECULAR_UNCONSTRAINED, RefineSettings
    from ntp_engine.pipeline.fit_traces import FLAG_WIDTH_FROM_MATERIAL, pooled_widths, refine_fit

    n = 96
    dev, traces, start = _lobe_traces(n, 8, (0.3, 0.3), 0.05, 6.0, 5)
    for off in (0.5, 2.0):
        wrong = _material((0.3 * off, 0.3 * off))
        got = pooled_widths(
            dev, traces, start, np.arange(n), np.zeros(n, np.int64), wrong, RefineSettings(), None, None
        )
        np.testing.assert_allclose(got.alpha, [[0.3, 0.3]], rtol=0.1)
        np.testing.assert_allclose(got.rho_s, [[6.0, 6.0, 6.0]], rtol=0.15)
        np.testing.assert_allclose(got.lobe_rho_d, [[0.05, 0.05, 0.05]], atol=0.01)  # its members' under that lobe
        np.testing.assert_allclose(got.rho_d, wrong.rho_d)
    out = refine_fit(dev, traces, start, RefineSettings())
    np.testing.assert_allclose(out["material_alpha"], [[0.3, 0.3]], rtol=0.1)
    took = out["flags"] & FLAG_WIDTH_FROM_MATERIAL != 0
    assert took.mean() > 0.25 and (out["flags"][took] & FLAG_SPECULAR_UNCONSTRAINED == 0).all()
    np.testing.assert_allclose(out["alpha"][took], np.broadcast_to(out["material_alpha"], (took.sum(), 2)))
    assert abs(np.median(out["rho_d"][took]) - 0.05) < 0.01


def test_a_broad_lobes_texels_without_one_of_their_own_join_its_material():
    """A rough metal (alpha 0.5, rho_s 9, rho_d 0.05) seen in 4 entries per texel: a broad lobe's
    light looks diffuse, so many texels keep no lobe of their own and, judged without one, look 3x
    brighter than they are. Judged under the material's lobe they are its colour, and take its lobe
    (before, 51 of the 192 were taken for matte, 45% took the material's lobe)."""
    from ntp_engine.fit.refine import FLAG_FROM_MATERIAL, RefineSettings
    from ntp_engine.pipeline.fit_traces import refine_fit

    dev, traces, start = _lobe_traces(192, 4, (0.5, 0.5), 0.05, 9.0, 7)
    out = refine_fit(dev, traces, start, RefineSettings())
    assert (out["material"] == -1).mean() < 0.2, np.unique(out["material"], return_counts=True)
    assert (out["flags"] & FLAG_FROM_MATERIAL != 0).mean() > 0.5


def test_an_isotropic_own_lobe_takes_its_anisotropic_materials_width_at_its_neighbours_turn():
    """Brushed traces (0.3 x 0.03) whose own answers came out isotropic (0.1), their tangents 60 deg
    off: the material's lobe at that tangent costs many of the traces more than their own, and where
    taken points 60 deg off; tried at the turn their neighbours point along (here: the truth's), it
    explains them better — they take the material's width and that tangent."""
    from ntp_engine.fit.refine import RefineSettings
    from ntp_engine.pipeline.fit_traces import FLAG_WIDTH_FROM_MATERIAL, _widths_from_materials

    n = 64
    dev, traces, start = _lobe_traces(n, 16, (0.3, 0.03), 0.1, 3.0, 11)
    truth = start["t_loc"].copy()
    turn = np.radians(60.0)
    t, nrm = start["t_loc"], start["n_loc"]
    start["t_loc"] = np.cos(turn) * t + np.sin(turn) * np.cross(nrm, t)
    start["alpha"][:] = 0.1
    start["material"] = np.zeros(n, np.int64)
    taken = []
    for back in (None, np.full(n, -turn)):
        fit = {k: v.copy() for k, v in start.items()}
        _widths_from_materials(
            dev, traces, fit, np.arange(n), _material((0.3, 0.03)), RefineSettings(), None, None, back
        )
        took = fit["flags"] & FLAG_WIDTH_FROM_MATERIAL != 0
        taken.append(took.mean())
        if back is None:  # only its own tangent: the lobe, where taken, points 60 deg off
            np.testing.assert_allclose(fit["t_loc"], start["t_loc"])
            continue
        np.testing.assert_allclose(fit["alpha"][took], np.broadcast_to([0.3, 0.03], (took.sum(), 2)))
        cos = np.abs((fit["t_loc"][took] * truth[took]).sum(1))
        error = np.degrees(np.arccos(np.clip(cos, 0, 1)))
        assert (error < 1.0).mean() > 0.9  # the rest: traces that cannot tell the two apart
    assert taken[1] > 0.9 and taken[1] > taken[0] + 0.2


def test_a_materials_lobe_is_isotropic_unless_its_members_traces_together_show_otherwise():
    """A sharp isotropic lobe (alpha 0.02, the lacquer's kind) whose members' median came out
    0.16 x 0.04 pools isotropic at the truth (profiled axis by axis from the median, it stayed
    0.16 x 0.04); a brushed lobe (0.3 x 0.03) whose median came out 0.3 x 0.06 stays anisotropic,
    both axes within 15%."""
    from ntp_engine.fit.refine import RefineSettings
    from ntp_engine.pipeline.fit_traces import pooled_widths

    n = 96
    for truth, median, seed in (((0.02, 0.02), (0.16, 0.04), 6), ((0.3, 0.03), (0.3, 0.06), 7)):
        dev, traces, start = _lobe_traces(n, 16, truth, 0.1, 3.0, seed)
        got = pooled_widths(
            dev, traces, start, np.arange(n), np.zeros(n, np.int64), _material(median), RefineSettings(), None, None
        )
        np.testing.assert_allclose(got.alpha, [truth], rtol=0.15)


def test_a_materials_width_that_varies_along_the_object_is_a_field():
    """A lacquer whose isotropic width runs 0.02 -> 0.25 along a 10 cm strip (the gallery dome's,
    around it), 16 entries per texel: its members' traces together make a width field, which
    gives each point the width its neighbours' traces prefer (median |log ratio| < 0.2 where the
    one pooled width is > 0.6 off); the same lacquer at one width gets none."""
    from ntp_engine.fit.refine import RefineSettings
    from ntp_engine.pipeline.fit_traces import pooled_widths
    from ntp_engine.pipeline.texels import Texels

    n = 192
    x = np.linspace(0.0, 0.1, n)
    truth = np.exp(np.log(0.02) + np.log(0.25 / 0.02) * x / 0.1)
    z = np.zeros(n, np.int64)
    strip = Texels(
        (1, n),
        z,
        np.arange(n),
        z,
        np.tile([1.0, 0, 0], (n, 1)),
        np.stack([x, 0 * x, 0 * x], 1),
        np.tile([0, 0, 1.0], (n, 1)),
        np.tile([1.0, 0, 0], (n, 1)),
    )
    for widths in (np.stack([truth, truth], 1), (0.07, 0.07)):
        dev, traces, start = _lobe_traces(n, 16, widths, 0.1, 3.0, 13)
        got = pooled_widths(dev, traces, start, np.arange(n), z, _material((0.07, 0.07)), RefineSettings(), strip, None)
        field = got.width[0]
        if isinstance(widths, tuple):
            assert field is None
            continue
        assert field is not None
        at = got.alpha_at(z, strip.position)
        np.testing.assert_allclose(at[:, 0], at[:, 1])
        assert np.median(np.abs(np.log(at[:, 0] / truth))) < 0.2
        assert np.median(np.abs(np.log(got.alpha[0, 0] / truth))) > 0.6


def test_members_own_tangents_do_not_make_a_sharp_isotropic_lobe_anisotropic():
    """A mirror-sharp isotropic lobe (alpha 0.006, the lacquer's) seen through an LED or two, each
    member's tangent turned to where an elongated lobe (0.012 x 0.006) fits its trace best, as its
    own solve would: pooled with those tangents from a median of 0.028 x 0.006, the material's lobe
    is isotropic at the truth. (On these exact traces the elongated lobe does not win even with the
    members' tangents unpaid; on the gallery box's rendered ones it did, docs/accuracy.md; the
    accounting itself: ``test_materials``.)"""
    from ntp_engine.fit.refine import RefineSettings, lobe_costs
    from ntp_engine.pipeline.fit_traces import pooled_widths, refine_inputs

    n, truth = 96, (0.006, 0.006)
    dev, traces, start = _lobe_traces(n, 16, truth, 0.1, 3.0, 12)
    inp = refine_inputs(dev, traces, torch.arange(n), start, None, None)
    # each member's tangent: of 12 turns, where the elongated lobe fits its trace best
    t, nrm = start["t_loc"], start["n_loc"]
    turns = np.radians(np.arange(0.0, 180.0, 15.0))
    costs = []
    for turn in turns:
        tt = np.cos(turn) * t + np.sin(turn) * np.cross(nrm, t)
        at = inp.start._replace(tangent=torch.as_tensor(tt, dtype=inp.start.tangent.dtype))
        c, _, _ = lobe_costs(dev, inp.entries, inp.mask, at, torch.tensor([[[0.012, 0.006]]]).expand(n, 1, 2))
        costs.append(c[:, 0].numpy())
    best = turns[np.argmin(np.stack(costs, 1), 1)]
    start["t_loc"] = np.cos(best)[:, None] * t + np.sin(best)[:, None] * np.cross(nrm, t)
    got = pooled_widths(
        dev, traces, start, np.arange(n), np.zeros(n, np.int64), _material((0.028, 0.006)), RefineSettings(), None, None
    )
    np.testing.assert_allclose(got.alpha, [truth], rtol=0.15)


def _square():
    """A flat 16 mm square's atlas (32², 0.5 mm texels) with its curvature and uv per metre."""
    from ntp_engine.io.mesh import Mesh, smooth_normals
    from ntp_engine.pipeline.texels import rasterize

    v = np.array([[0, 0, 0], [0.016, 0, 0], [0.016, 0.016, 0], [0, 0.016, 0.0]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    return rasterize(Mesh(v, f, v[:, :2] / 0.016, smooth_normals(v, f)), (32, 32), curvature=True)


def _square_in_two_views(distance: float, pixels: tuple[float, float]):
    """``_square``'s atlas and its traces: two views ``distance`` (m) straight above it, a fraction
    of a pixel apart, every pixel ``pixels[0]`` left of the middle and ``pixels[1]`` right of it
    (grey)."""
    tx = _square()
    y = np.where(tx.col[:, None] < 16, *pixels) * np.ones(3)
    rows = []
    for shift in (0.0, 0.0013):
        R = np.diag([1.0, -1.0, -1.0])
        x = tx.position @ R.T + [-0.008 + shift, 0.008, distance]
        n, t = np.tile(R @ [0, 0, 1.0], (len(tx), 1)), np.tile(R @ [1.0, 0, 0], (len(tx), 1))
        rows.append(np.concatenate([y, x, n, t], 1))
    entries = torch.as_tensor(np.stack(rows, 1).reshape(-1, 12), dtype=torch.float32)
    return tx, RaggedTraces(entries, torch.arange(0, 2 * len(tx) + 1, 2))


def test_each_entry_gets_the_albedo_its_pixel_may_blend_in_near_an_edge_only(monkeypatch):
    """``with_albedo_blend`` on a flat square seen from two poses, the albedo 0.3 left of the middle
    and 0.7 right of it: entries of texels two or more texels from the edge blend nothing, some next
    to it up to the step; in blocks it is the same as every entry at once."""
    from ntp_engine.fit.footprint import albedo_blend, sample_points
    from ntp_engine.io.maps import texel_uv

    tx, traces = _square_in_two_views(0.3, (0.5, 0.5))
    entries = traces.entries
    rho_d = np.where(tx.col[:, None] < 16, 0.3, 0.7) * np.ones(3)
    monkeypatch.setattr(fit_traces_module, "BLEND_ENTRIES", 7)
    dev = load_scanner()
    out = fit_traces_module.with_albedo_blend(dev, traces, rho_d, tx).albedo_blend
    assert out is not None and out.shape == (len(entries), 3)
    delta, weight = sample_points(dev, entries[:, None, :], torch.ones(len(entries), 1, dtype=torch.bool))
    texel = np.repeat(np.arange(len(tx)), 2)
    uv = texel_uv((32, 32))[tx.row, tx.col][texel]
    direct = albedo_blend(delta, weight, uv, tx.uv_per_metre[texel], _map(tx, rho_d))
    torch.testing.assert_close(out, direct[:, 0].float())
    far = np.abs(tx.col[texel] + 0.5 - 16) > 2.5
    assert out[far].abs().max().item() < 1e-6
    assert (out >= 0).all() and 0.005 < out[~far].max().item() <= 0.4


def test_the_edge_pass_starts_from_the_first_pass_and_seeks_a_lobe_only_where_it_kept_one(monkeypatch):
    """``refine_fit`` on a flat square of two albedos (0.3 | 0.7) seen in two views: the texels next
    to the edge are refined again with the blend as noise, from the first pass's answers in
    ``EDGE_ROUNDS`` without the multi-start, the pulls centred on the start; those whose first pass
    kept no lobe seek none there (their warm start says no highlight); their answers have none."""
    from ntp_engine.fit.geometry import FLAG_NO_HIGHLIGHT
    from ntp_engine.fit.refine import FLAG_SPECULAR_UNCONSTRAINED, RefineSettings

    tx, traces = _square_in_two_views(0.8, (0.02, 0.05))  # farther: a pixel spans ~a texel
    dev = load_scanner()
    N = len(tx)
    start = {"n_loc": np.tile([0.0, 0, 1], (N, 1)), "t_loc": np.tile([1.0, 0, 0], (N, 1))}
    start |= {"alpha": np.full((N, 2), 0.2), "rho_d": np.full((N, 3), 0.5), "rho_s": np.full((N, 3), 1.0)}
    start["flags"] = np.zeros(N, np.int64)
    calls = []
    real = fit_traces_module._refine_texels

    def spy(scanner, traces, fit, start, todo, settings, progress, texels, support, name, centre=None):
        calls.append((name, todo.numpy().copy(), {k: v.copy() for k, v in start.items()}, settings, centre))
        calls[-1] += ({k: v.copy() for k, v in fit.items()},)
        real(scanner, traces, fit, start, todo, settings, progress, texels, support, name, centre)

    monkeypatch.setattr(fit_traces_module, "_refine_texels", spy)
    out = fit_traces_module.refine_fit(dev, traces, start, RefineSettings(materials=False), texels=tx)
    assert [c[0] for c in calls] == ["refine", "albedo edges"]
    _, edges, warm, settings, centre, first = calls[1]
    assert 0 < len(edges) < N
    assert settings.rounds == fit_traces_module.EDGE_ROUNDS and not settings.starts
    for key in ("n_loc", "t_loc", "alpha", "rho_d", "rho_s"):
        np.testing.assert_array_equal(warm[key], first[key])  # the first pass's answers
        np.testing.assert_array_equal(centre[key], start[key])  # the pulls: the start's
    lobeless = first["flags"][edges] & FLAG_SPECULAR_UNCONSTRAINED != 0
    assert lobeless.any()
    np.testing.assert_array_equal(warm["flags"][edges] & FLAG_NO_HIGHLIGHT != 0, lobeless)
    assert (out["rho_s"][edges[lobeless]] == 0).all()


def _map(tx, values):
    img = np.zeros((*tx.shape, values.shape[1]))
    img[tx.row, tx.col] = values
    return img


def test_normals_are_fused_within_each_material_with_tangents_kept_orthogonal():
    from ntp_engine.pipeline.fit_traces import fuse_normals
    from ntp_engine.pipeline.texels import Texels

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
    fit = {
        "n_loc": n_loc.copy(),
        "t_loc": t_loc,
        "std": np.tile([np.degrees(0.02 * np.sqrt(2)), 5.0, 0.1, 0.1], (N, 1)),
        "material": material,
    }
    fit["std"][0, 0] = np.nan  # no normal std: kept
    fuse_normals(fit, texels, np.arange(N))
    tilt_before = np.degrees(np.arccos(n_loc[material == 0, 2]))
    tilt_after = np.degrees(np.arccos(np.clip(fit["n_loc"][material == 0, 2], -1, 1)))
    assert np.median(tilt_after) < 0.5 * np.median(tilt_before)
    np.testing.assert_allclose(fit["n_loc"][material == -1], n_loc[material == -1], atol=1e-12)  # not the other's
    np.testing.assert_allclose(fit["n_loc"][0], n_loc[0])
    np.testing.assert_allclose((fit["n_loc"] * fit["t_loc"]).sum(1), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(fit["t_loc"], axis=1), 1.0)
    assert np.nanmedian(fit["std"][material == 0, 0]) < 0.5 * np.degrees(0.02 * np.sqrt(2))


def test_the_albedos_next_to_an_edge_come_back_sharper_from_the_entries_pixel_samples():
    """A flat square 0.2 | 0.8 seen from 8 poses a fraction of a pixel apart (a pixel spans ~a
    texel), each entry's pixel the diffuse light times the albedos its four taps see (as the camera
    samples them): each texel's own answer is blurred next to the edge; ``sharpen_albedos`` on the
    texels beside it brings them back more than half way, holds the rest, and never gives NaN."""
    from ntp_engine.fit.albedo_map import tap_texels
    from ntp_engine.fit.footprint import sample_points
    from ntp_engine.fit.refine import RefineSettings, Start, predicted_light

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
    diffuse, _, _ = predicted_light(dev, entries, mask, Start.from_fit(fit, np.arange(N)))
    delta, weight = sample_points(dev, entries, mask)
    index = np.full(tx.shape, -1, np.int64)
    index[tx.row, tx.col] = np.arange(N)
    taps, w = tap_texels(delta.numpy(), weight.numpy(), tx.uv, tx.uv_per_metre, index)
    y = diffuse.numpy() * (w[..., None] * truth[taps]).sum(2)
    entries[..., :3] = torch.as_tensor(y, dtype=torch.float32)
    d = diffuse.numpy()
    fit["rho_d"] = (d * y).sum(1) / (d * d).sum(1)  # each texel's own answer
    traces = RaggedTraces(entries.reshape(-1, 12), torch.arange(0, V * N + 1, V))
    beside = np.nonzero(np.abs(tx.col + 0.5 - 16) < 3)[0]
    own = fit["rho_d"].copy()
    assert np.abs(own[beside] - truth[beside]).max() > 0.02  # blurred
    fit_traces_module.sharpen_albedos(dev, traces, fit, torch.as_tensor(beside), RefineSettings(), tx)
    out = fit["rho_d"]
    assert np.isfinite(out).all()
    np.testing.assert_array_equal(np.delete(out, beside, 0), np.delete(own, beside, 0))
    before, after = (np.sqrt(((a[beside] - truth[beside]) ** 2).mean()) for a in (own, out))
    assert after < 0.5 * before


def test_refine_fit_sharpens_the_albedos_of_the_edge_pass_texels_only_when_asked(monkeypatch):
    """``refine_fit`` solves the albedo map (``sharpen_albedos``) over texels the edge pass refined
    (those that may blend ``MIN_BLEND`` or more), after every other step;
    ``RefineSettings(albedo_map=False)`` leaves it out."""
    from ntp_engine.fit.refine import RefineSettings

    tx, traces = _square_in_two_views(0.8, (0.05, 0.3))
    dev = load_scanner()
    N = len(tx)
    start = {"n_loc": np.tile([0.0, 0, 1], (N, 1)), "t_loc": np.tile([1.0, 0, 0], (N, 1))}
    start |= {"alpha": np.full((N, 2), 0.2), "rho_d": np.full((N, 3), 0.5), "rho_s": np.full((N, 3), 1.0)}
    start["flags"] = np.zeros(N, np.int64)
    passes, sharpened = [], []
    real_pass, real_sharpen = fit_traces_module._refine_texels, fit_traces_module.sharpen_albedos

    def spy_pass(scanner, traces, fit, start, todo, settings, progress, texels, support, name, centre=None):
        passes.append((name, todo.numpy().copy()))
        real_pass(scanner, traces, fit, start, todo, settings, progress, texels, support, name, centre)

    def spy_sharpen(scanner, traces, fit, idx, *args, **kwargs):
        sharpened.append((idx.numpy().copy(), fit["n_loc"].copy()))
        real_sharpen(scanner, traces, fit, idx, *args, **kwargs)

    monkeypatch.setattr(fit_traces_module, "_refine_texels", spy_pass)
    monkeypatch.setattr(fit_traces_module, "sharpen_albedos", spy_sharpen)
    out = fit_traces_module.refine_fit(dev, traces, start, RefineSettings(materials=False), texels=tx)
    assert [p[0] for p in passes] == ["refine", "albedo edges"] and len(sharpened) == 1
    assert 0 < len(sharpened[0][0]) and np.isin(sharpened[0][0], passes[1][1]).all()
    np.testing.assert_array_equal(sharpened[0][1], out["n_loc"])  # after the normals were fused
    assert np.isfinite(out["rho_d"]).all()
    passes.clear()
    fit_traces_module.refine_fit(dev, traces, start, RefineSettings(materials=False, albedo_map=False), texels=tx)
    assert len(sharpened) == 1
