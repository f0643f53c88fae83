import numpy as np
import pytest
import torch

from ntp_engine.learn.inference import RaggedTraces
from ntp_engine.learn.ragged import concatenated_rows


def test_bad_ragged_input():
    with pytest.raises(ValueError):
        RaggedTraces(torch.zeros(4, 10), torch.tensor([0, 4]))
    with pytest.raises(ValueError):
        RaggedTraces(torch.zeros(4, 12), torch.tensor([0, 3]))


def test_padded_subsampling_spreads_over_the_trace():
    entries = torch.arange(20, dtype=torch.float32)[:, None].repeat(1, 12)
    tr = RaggedTraces(entries, torch.tensor([0, 2, 12, 20]))
    full, m = tr.padded(torch.tensor([0, 1, 2]))
    assert m.sum(1).tolist() == [2, 10, 8] and full.shape == (3, 10, 12)
    sub, ms = tr.padded(torch.tensor([0, 1, 2]), max_views=4)
    assert ms.sum(1).tolist() == [2, 4, 4]
    assert sub[1, :, 0].tolist() == [2.0, 5.0, 8.0, 11.0]  # first, evenly spread, last
    assert sub[0, :2, 0].tolist() == [0.0, 1.0] and (sub[0, 2:] == 0).all()


def test_in_range_only_keeps_the_flagged_entries_per_trace():
    entries = torch.arange(7 * 12, dtype=torch.float32).reshape(7, 12)
    keep = torch.tensor([1, 0, 1, 1, 1, 0, 0], dtype=torch.bool)
    tr = RaggedTraces(entries, torch.tensor([0, 3, 3, 7]), keep)
    only = tr.in_range_only()
    assert only.lengths.tolist() == [2, 0, 2] == tr.in_range_lengths().tolist()
    torch.testing.assert_close(only.entries, entries[keep])
    assert RaggedTraces(entries, torch.tensor([0, 7])).in_range_only().lengths.tolist() == [7]
    with pytest.raises(ValueError):
        RaggedTraces(entries, torch.tensor([0, 7]), keep[:3])


def test_block_is_the_traces_of_its_range():
    entries = torch.arange(7 * 12, dtype=torch.float32).reshape(7, 12)
    keep = torch.tensor([1, 0, 1, 1, 1, 0, 0], dtype=torch.bool)
    tr = RaggedTraces(entries, torch.tensor([0, 3, 3, 7]), keep)
    b = tr.block(1, 3)
    assert b.num_traces == 2 and b.lengths.tolist() == [0, 4]
    torch.testing.assert_close(b.entries, entries[3:7])
    assert b.in_range is not None and b.in_range.tolist() == [1, 1, 0, 0]
    assert tr.block(0, 0).num_traces == 0 and len(tr.block(0, 0).entries) == 0
    assert b.entries.data_ptr() == entries[3:].data_ptr()  # a view: a block costs no copy


def test_in_range_lengths_counted_in_chunks_equal_the_copy(monkeypatch):
    """Chunks of a few entries (traces longer than a chunk, empty ones, none at all)."""
    from ntp_engine.learn import ragged

    gen = torch.Generator().manual_seed(0)
    lengths = torch.randint(0, 12, (200,), generator=gen)
    offsets = torch.cat([torch.zeros(1, dtype=torch.int64), lengths.cumsum(0)])
    E = int(offsets[-1])
    tr = RaggedTraces(torch.zeros(E, 12), offsets, torch.rand(E, generator=gen) > 0.3)
    monkeypatch.setattr(ragged, "COUNT_CHUNK", 5)
    assert torch.equal(tr.in_range_lengths(), tr.in_range_only().lengths)
    empty = RaggedTraces(torch.zeros(0, 12), torch.zeros(1, dtype=torch.int64), torch.zeros(0, dtype=torch.bool))
    assert empty.in_range_lengths().shape == (0,)


def test_spans_cover_every_trace_within_the_budget_or_one_trace_alone():
    from ntp_engine.learn.ragged import spans

    offsets = np.array([0, 3, 3, 10, 12, 13, 20])  # lengths 3, 0, 7, 2, 1, 7
    assert list(spans(offsets, 5)) == [(0, 2), (2, 3), (3, 5), (5, 6)]
    assert list(spans(offsets, 100)) == [(0, 6)]
    assert list(spans(np.zeros(1, np.int64), 5)) == []


def test_spread_keeps_what_padded_keeps():
    entries = torch.arange(20, dtype=torch.float32)[:, None].repeat(1, 12)
    tr = RaggedTraces(entries, torch.tensor([0, 2, 2, 12, 20]))
    sub = tr.spread(4)
    assert sub.lengths.tolist() == [2, 0, 4, 4]
    padded, mask = tr.padded(torch.arange(4), max_views=4)
    torch.testing.assert_close(sub.entries, padded[mask])


def test_shadow_masks_are_those_of_the_padded_entries():
    """``shadow_at`` reads the rows ``padded`` reads (spread, zeros past a trace's length);
    ``block`` carries the column, ``in_range_only`` drops it; without one every mask is 0."""
    entries = torch.arange(20, dtype=torch.float32)[:, None].repeat(1, 12)
    shadow = torch.arange(20, dtype=torch.int64) << 40  # high bits too
    tr = RaggedTraces(entries, torch.tensor([0, 2, 2, 12, 20]), shadow=shadow)
    idx = torch.tensor([2, 0, 1])
    padded, mask = tr.padded(idx, max_views=4)
    masks = tr.shadow_at(*tr.padded_rows(idx, max_views=4))
    assert masks.shape == mask.shape and (masks[~mask] == 0).all()
    assert torch.equal(masks[mask], padded[mask][:, 0].long() << 40)
    b = tr.block(2, 4)
    assert b.shadow is not None and torch.equal(b.shadow, shadow[2:])
    assert RaggedTraces(entries, tr.offsets, shadow > 0, shadow).in_range_only().shadow is None
    assert not RaggedTraces(entries, tr.offsets).shadow_at(*tr.padded_rows(idx)).any()
    with pytest.raises(ValueError):
        RaggedTraces(entries, tr.offsets, shadow=shadow[:3])


def test_spread_rows_run_over_the_usable_entries_only():
    """``spread_rows`` spreads over the entries ``usable`` allows, in trace order; a trace with
    none keeps none; with every entry usable it is ``padded_rows``'s own spread."""
    from ntp_engine.learn.ragged import spread_rows

    entries = torch.arange(20, dtype=torch.float32)[:, None].repeat(1, 12)
    tr = RaggedTraces(entries, torch.tensor([0, 2, 2, 12, 20]))
    every, mask = tr.padded_rows(torch.tensor([2, 0, 1, 3]))
    rows, keep = spread_rows(every, mask & (every % 2 == 1), max_views=3)
    got = [rows[i][keep[i]].tolist() for i in range(4)]
    assert got == [[3, 7, 11], [1], [], [13, 17, 19]]  # of 5 odd rows: 1st, 3rd, 5th; of 4: 1st, 3rd, 4th
    every, mask = tr.padded_rows(torch.tensor([2, 3]))
    all_rows, all_mask = spread_rows(every, mask, max_views=3)
    plain_rows, plain_mask = tr.padded_rows(torch.tensor([2, 3]), max_views=3)
    assert torch.equal(all_rows[all_mask], plain_rows[plain_mask])


def test_albedo_blends_are_those_of_the_padded_entries():
    """``albedo_blend_at`` reads the rows ``padded`` reads (zeros past a trace's length); ``block``
    carries the column; without one it is None; a column of the wrong shape is refused."""
    entries = torch.arange(20, dtype=torch.float32)[:, None].repeat(1, 12)
    offset = torch.arange(60, dtype=torch.float32).reshape(20, 3)
    tr = RaggedTraces(entries, torch.tensor([0, 2, 2, 12, 20]), albedo_blend=offset)
    idx = torch.tensor([2, 0, 1])
    padded, mask = tr.padded(idx, max_views=4)
    got = tr.albedo_blend_at(*tr.padded_rows(idx, max_views=4))
    assert got is not None and got.shape == (*mask.shape, 3) and (got[~mask] == 0).all()
    assert torch.equal(got[mask][:, 0], 3 * padded[mask][:, 0])
    b = tr.block(2, 4)
    assert b.albedo_blend is not None and torch.equal(b.albedo_blend, offset[2:])
    assert RaggedTraces(entries, tr.offsets).albedo_blend_at(*tr.padded_rows(idx)) is None
    with pytest.raises(ValueError):
        RaggedTraces(entries, tr.offsets, albedo_blend=offset[:, :2])


def test_only_keeps_the_chosen_traces_entries_and_columns_in_place():
    entries = torch.arange(10, dtype=torch.float32)[:, None].repeat(1, 12)
    flags = torch.tensor([1, 0, 1, 1, 0, 1, 1, 1, 1, 0], dtype=torch.bool)
    shadow = torch.arange(10, dtype=torch.int64) * 3
    tr = RaggedTraces(entries, torch.tensor([0, 2, 2, 5, 9, 10]), flags, shadow)
    sub = tr.only(torch.tensor([2, 4]))
    assert sub.num_traces == 5 and sub.lengths.tolist() == [0, 0, 3, 0, 1]  # trace i is still texel i
    assert sub.entries[:, 0].tolist() == [2, 3, 4, 9]
    assert sub.in_range.tolist() == [True, True, False, False] and sub.shadow.tolist() == [6, 9, 12, 27]
    assert tr.only(torch.tensor([], dtype=torch.int64)).lengths.sum() == 0


def test_concatenated_rows_are_each_traces_rows_in_the_given_order():
    rows, offsets = concatenated_rows(torch.tensor([5, 0, 9]), torch.tensor([3, 2, 0]))
    assert rows.tolist() == [5, 6, 7, 0, 1] and offsets.tolist() == [0, 3, 5, 5]
    rows, offsets = concatenated_rows(torch.zeros(0, dtype=torch.int64), torch.zeros(0, dtype=torch.int64))
    assert rows.tolist() == [] and offsets.tolist() == [0]
