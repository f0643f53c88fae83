import numpy as np

from ntp_engine.io.tuned import retuned
from ntp_engine.refine import albedo_map
from ntp_engine.refine.albedo_map import sharpened_albedos, tap_texels


def _row_atlas(width: int) -> np.ndarray:
    """A one-row map of ``width`` texels, texel i at column i."""
    return np.arange(width, dtype=np.int64)[None, :]


def test_each_tap_counts_for_the_texel_its_surface_point_lands_in():
    """Taps 0.6 texel right land in the next texel, 0.4 in their own; a tap off the atlas counts for
    the entry's own texel; an entry with no weighed tap reads its own texel with weight 1."""
    index = np.full((1, 8), -1, np.int64)
    index[0, 1:7] = np.arange(6)  # texels 0..5 at columns 1..6; columns 0 and 7 are no texel's
    uv = np.array([[(c + 0.5) / 8, 0.5] for c in (3, 6)])  # texels 2 and 5
    per_metre = np.tile(np.diag([0.125 / 1e-3, 1.0]), (2, 1, 1))  # 1 mm along t^ is one texel
    delta = np.zeros((2, 2, 4, 2))
    delta[:, 0, 1, 0], delta[:, 0, 2, 0], delta[:, 0, 3, 0] = 0.6e-3, 0.4e-3, -0.6e-3
    weight = np.array([[[0.4, 0.3, 0.2, 0.1], [0.0, 0.0, 0.0, 0.0]]] * 2)
    taps, w = tap_texels(delta, weight, uv, per_metre, index)
    np.testing.assert_array_equal(taps[0, 0], [2, 3, 2, 1])
    np.testing.assert_array_equal(taps[1, 0], [5, 5, 5, 4])  # 0.6 texel right of texel 5: off the atlas
    np.testing.assert_array_equal(w[:, 0], weight[:, 0])
    np.testing.assert_array_equal(taps[:, 1, 0], [2, 5])
    np.testing.assert_array_equal(w[:, 1], [[1.0, 0, 0, 0]] * 2)


def _blended_entries(truth: np.ndarray, per_texel: int, seed: int):
    """Entries of every texel of a row whose pixels blend the texel's albedo with its left and right
    neighbours' at random shares (a sub-pixel sample over a ~texel footprint), diffuse light 0.5-1.5
    per entry; each as (diffuse, pixel, inv_sigma, taps, weights)."""
    rng = np.random.default_rng(seed)
    T = len(truth)
    texel = np.repeat(np.arange(T), per_texel)
    M = len(texel)
    side = rng.uniform(0, 0.5, M)
    left = rng.random(M) < 0.5
    taps = np.stack([texel, np.where(left, texel - 1, texel + 1), texel, texel], 1).clip(0, T - 1)
    w = np.stack([1 - side, side, np.zeros(M), np.zeros(M)], 1)
    d = rng.uniform(0.5, 1.5, (M, 1)) * np.ones(3)
    y = d * (w[..., None] * truth[taps]).sum(1)
    return d, y, np.full((M, 3), 1 / 0.002), taps, w, texel


def _own_answers(d, y, texel, T):
    """Each texel's own least-squares albedo (its entries read as if they saw only it): blurred."""
    num, den = np.zeros((T, 3)), np.zeros((T, 3))
    np.add.at(num, texel, d * y)
    np.add.at(den, texel, d * d)
    return num / den


def test_an_albedo_step_blurred_by_the_pixel_samples_comes_back_sharp(monkeypatch):
    """A row of texels 0.2 | 0.8 whose entries blend the neighbours' albedo: each texel's own answer
    is blurred next to the step (0.315 | 0.714); solved together (every texel) under a weak pull to
    those answers they come back within 0.005 of the truth; under the default pull (the demo's and
    gallery's choice) they move toward it, less (the step is the system's least determined mode:
    AᵀA's smallest eigenvalue is ~0.4 of its median diagonal); never NaN."""
    truth = np.where(np.arange(20) < 10, 0.2, 0.8)[:, None] * np.ones(3)
    d, y, s, taps, w, texel = _blended_entries(truth, 24, 0)
    own = _own_answers(d, y, texel, 20)
    step = [9, 10]
    assert (np.abs(own[step] - truth[step]) > 0.08).all()  # the blur
    default = sharpened_albedos(d, y, s, taps, w, own, np.arange(20))
    assert np.isfinite(default).all()
    assert (np.abs(default[step] - truth[step]) < np.abs(own[step] - truth[step])).all()
    monkeypatch.setattr(albedo_map, "TUNING", retuned(albedo_map.TUNING, "albedo_map", prior_weight=0.01))
    weak = sharpened_albedos(d, y, s, taps, w, own, np.arange(20))
    assert np.abs(weak - truth).max() < 0.005


def test_texels_not_solved_are_held_and_a_highlight_does_not_move_the_answer():
    """Only the texels named are solved (the others hold their values and enter the pixels they
    share as known); an entry far above its prediction (a glint the lobe missed) is down-weighted
    (Cauchy), and one with 1/sigma 0 (clipped) is not read."""
    truth = np.where(np.arange(20) < 10, 0.2, 0.8)[:, None] * np.ones(3)
    d, y, s, taps, w, texel = _blended_entries(truth, 24, 1)
    own = _own_answers(d, y, texel, 20)
    start = own.copy()
    start[:8], start[12:] = truth[:8], truth[12:]  # far from the step, the own answers are right
    solved = np.arange(8, 12)
    y_glint, s_clip = y.copy(), s.copy()
    glint = np.nonzero(texel == 9)[0][:2]
    y_glint[glint] += 2.0
    clipped = np.nonzero(texel == 10)[0][:3]
    y_glint[clipped], s_clip[clipped] = 5.0, 0.0
    out = sharpened_albedos(d, y_glint, s_clip, taps, w, start, solved)
    np.testing.assert_array_equal(np.delete(out, solved, 0), np.delete(start, solved, 0))
    assert np.abs(out[solved] - truth[solved]).max() < 0.02


def test_a_solved_texel_no_entry_reaches_keeps_its_value():
    """A texel named but reached by no entry (all read elsewhere, or none usable) keeps its start."""
    truth = np.full((6, 3), 0.5)
    d, y, s, taps, w, texel = _blended_entries(truth, 8, 2)
    s[texel == 5] = 0.0
    keep = np.where(texel == 4, 1.0, w[:, 0])
    w = np.stack([keep, np.where(texel == 4, 0.0, w[:, 1]), w[:, 2], w[:, 3]], 1)
    start = np.full((6, 3), 0.3)
    out = sharpened_albedos(d, y, s, taps, w, start, np.array([5]))
    np.testing.assert_allclose(out[5], start[5])
    np.testing.assert_array_equal(sharpened_albedos(d, y, s, taps, w, start, np.array([], np.int64)), start)


def test_the_joint_solve_reports_each_of_its_solves(tmp_path):
    """Its progress stage "albedo solve" (one of ``passes.PROGRESS_STAGES``) counts every channel's
    rounds to its end: at 1024² the solve runs ~a minute after the albedo map's batches."""
    import json

    from ntp_engine.io.progress import Progress
    from ntp_engine.refine.passes import PROGRESS_STAGES
    from ntp_engine.refine.settings import TUNING

    truth = np.where(np.arange(20) < 10, 0.2, 0.8)[:, None] * np.ones(3)
    d, y, s, taps, w, texel = _blended_entries(truth, 24, 3)
    log = tmp_path / "progress.jsonl"
    sharpened_albedos(d, y, s, taps, w, _own_answers(d, y, texel, 20), np.arange(20), Progress(json_path=log))
    rows = [json.loads(line) for line in log.read_text().splitlines()]
    assert {row["stage"] for row in rows} == {"albedo solve"} and "albedo solve" in PROGRESS_STAGES
    assert rows[-1]["done"] == rows[-1]["total"] == 3 * TUNING.albedo_map.rounds
