import numpy as np
import torch

from ntp_engine.fit.texel_fit import TexelFit
from ntp_engine.io.tuned import retuned
from ntp_engine.learn.ragged import RaggedTraces
from ntp_engine.refine import inputs as inputs_module
from ntp_engine.scanner.device_file import load_scanner


def _traces_of(kinds: list[str]):
    """The scanner, a table of traces whose entries are of ``kinds`` (per trace, per entry: c clear,
    s shadowed — half the emitter groups hidden — g grazing; entry k's pixel red = k), the shadow
    masks per trace, and a start for each."""
    from ntp_engine.physics.emitter_blocks import shadow_groups

    dev = load_scanner()
    half = (1 << (len(shadow_groups(dev).points) // 2)) - 1  # half the groups hidden: shadowed
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
    return dev, traces, table, TexelFit.from_arrays(fit)


def test_refine_inputs_read_marginal_entries_only_where_too_few_others_are_left():
    """A texel with at least ``TUNING.inputs.min_clear_entries`` clear entries — neither shadowed by its mesh
    (over ``MAX_SHADOWED_DRIVE`` of the drive hidden) nor grazing (wo . n^ <= ``MIN_COS_VIEW``) —
    is refined on those alone; one with fewer reads its marginal entries too, with their masks,
    and is flagged ``marginal``."""
    from ntp_engine.refine.inputs import refine_inputs
    from ntp_engine.refine.settings import TUNING

    # kinds of each trace's entries (c clear, s shadowed, g grazing): plenty clear, too few, none, no entries
    kinds = ["csg" * 13 + "c", "c" * (TUNING.inputs.min_clear_entries - 1) + "sg" * 15, "sgsgs", ""]
    lengths = [len(t) for t in kinds]
    dev, traces, table, fit = _traces_of(kinds)
    N = len(kinds)
    inp = refine_inputs(dev, traces, torch.arange(N), fit)
    ent, mask, masks, marginal = inp.obs.entries, inp.obs.mask, inp.obs.shadow, inp.marginal
    assert inp.obs.support is None  # none asked for
    clear = [{k for k, c in enumerate(t) if c == "c"} for t in kinds]
    few = [len(c) < TUNING.inputs.min_clear_entries for c in clear]
    assert marginal.tolist() == [few[0], few[1], True, False]
    for i, n in enumerate(lengths):
        got = ent[i, mask[i], 0].long()
        usable = set(range(n)) if few[i] else clear[i]
        assert len(got) == min(len(usable), TUNING.inputs.refine_views) and set(got.tolist()) <= usable
        assert torch.equal(masks[i, mask[i]], table[i][got])
    assert not few[0] and few[1] and mask[2].sum() == 5  # both cases are there


def test_the_read_table_holds_what_the_refinement_reads_and_reading_it_again_reads_the_same(monkeypatch):
    """``read_traces``: per trace at most ``refine_views`` entries, those ``refine_inputs`` picks from
    the whole trace, every column carried; ``refine_inputs`` on it reads the same entries, masks
    and marginal flags — chosen in blocks smaller than a trace too."""
    from ntp_engine.refine.inputs import read_traces, refine_inputs
    from ntp_engine.refine.settings import TUNING

    few = TUNING.inputs.min_clear_entries - 1
    kinds = ["c" * 70, "csg" * 13 + "c", "c" * few + "sg" * 15, "sgsgs", "", "gc" * 3 + "s" * 30, "c" * 3]
    dev, traces, table, fit = _traces_of(kinds)
    traces.albedo_blend = torch.rand(len(traces.entries), 3)
    N = len(kinds)
    whole = refine_inputs(dev, traces, torch.arange(N), fit)
    monkeypatch.setattr(inputs_module, "TUNING", retuned(TUNING, "inputs", blend_entries=40))
    read = read_traces(dev, traces)
    assert (read.lengths <= TUNING.inputs.refine_views).all() and int(read.lengths[4]) == 0
    assert torch.equal(read.lengths, whole.obs.mask.sum(1))
    again = refine_inputs(dev, read, torch.arange(N), fit)
    assert torch.equal(again.marginal, whole.marginal)
    for a, b in ((again.obs.mask, whole.obs.mask), (again.obs.shadow, whole.obs.shadow)):
        assert torch.equal(a[:, : b.shape[1]], b) and not a[:, b.shape[1] :].any()
    V = whole.obs.mask.shape[1]
    assert torch.equal(again.obs.entries[:, :V], whole.obs.entries)
    assert torch.equal(again.obs.footprint.albedo_blend[:, :V], whole.obs.footprint.albedo_blend)
    assert torch.equal(read.in_range, (read.shadow == 0) & (read.entries[:, 8] < -0.5))  # carried row by row
    # a sample's table (most traces empty): the same entries, its blocks holding only traces with entries
    sample = traces.only(torch.tensor([1, 5]))
    padded = []
    real = RaggedTraces.padded_rows
    counted = lambda self, idx, *a: padded.append(len(idx)) or real(self, idx, *a)  # noqa: E731
    monkeypatch.setattr(RaggedTraces, "padded_rows", counted)
    part = read_traces(dev, sample)
    assert max(padded) <= 2 and torch.equal(part.lengths[[1, 5]], read.lengths[[1, 5]])
    assert torch.equal(part.entries, torch.cat([read.entries[read.offsets[i] : read.offsets[i + 1]] for i in (1, 5)]))


def _square():
    """A flat 16 mm square's atlas (32², 0.5 mm texels) with its curvature and uv per metre."""
    from ntp_engine.io.mesh import Mesh, smooth_normals
    from ntp_engine.io.texels import rasterize

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
    from ntp_engine.io.maps import texel_uv
    from ntp_engine.refine.footprint import albedo_blend, sample_points

    tx, traces = _square_in_two_views(0.3, (0.5, 0.5))
    entries = traces.entries
    rho_d = np.where(tx.col[:, None] < 16, 0.3, 0.7) * np.ones(3)
    monkeypatch.setattr(inputs_module, "TUNING", retuned(inputs_module.TUNING, "inputs", blend_entries=7))
    dev = load_scanner()
    out = inputs_module.with_albedo_blend(dev, traces, rho_d, tx).albedo_blend
    assert out is not None and out.shape == (len(entries), 3)
    delta, weight = sample_points(dev, entries[:, None, :], torch.ones(len(entries), 1, dtype=torch.bool))
    texel = np.repeat(np.arange(len(tx)), 2)
    uv = texel_uv((32, 32))[tx.row, tx.col][texel]
    direct = albedo_blend(delta, weight, uv, tx.uv_per_metre[texel], _map(tx, rho_d))
    torch.testing.assert_close(out, direct[:, 0].float())
    far = np.abs(tx.col[texel] + 0.5 - 16) > 2.5
    assert out[far].abs().max().item() < 1e-6
    assert (out >= 0).all() and 0.005 < out[~far].max().item() <= 0.4


def _map(tx, values):
    img = np.zeros((*tx.shape, values.shape[1]))
    img[tx.row, tx.col] = values
    return img
