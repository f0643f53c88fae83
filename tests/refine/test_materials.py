"""Basis materials: clusters of the texels that kept a lobe, their lobe rates, and the class costs
that assign every texel a lobe material or none."""

import dataclasses

import numpy as np
import pytest

from ntp_engine.refine.materials import (
    BasisMaterials,
    candidates,
    class_costs,
    clusters,
    colour_held,
    estimated_matte_share,
    judged_colour_costs,
    label_neighbours,
    lobe_clusters,
    local_shares,
    material_weight,
    pooled_scale,
    pooled_votes,
    second_wins,
)
from ntp_engine.refine.settings import TUNING


def _two_materials(rng: np.random.Generator, n: int = 200):
    """Texels of a blue glossy and a grey brushed material, with the scatter of a fit."""
    rho_d = np.concatenate([np.tile([0.05, 0.08, 0.3], (n, 1)), np.tile([0.2, 0.2, 0.2], (n, 1))])
    alpha = np.concatenate([np.tile([0.05, 0.05], (n, 1)), np.tile([0.3, 0.05], (n, 1))])
    rho_s = np.concatenate([np.full((n, 3), 3.0), np.full((n, 3), 1.0)])

    def jitter(shape: tuple[int, int]) -> np.ndarray:
        return np.exp(0.05 * rng.standard_normal(shape))

    return rho_d * jitter((2 * n, 3)), alpha * jitter((2 * n, 2)), rho_s * jitter((2 * n, 3))


def test_clusters_separate_distinct_groups_deterministically():
    rng = np.random.default_rng(0)
    f = np.concatenate([rng.normal(0, 0.3, (100, 3)), rng.normal(5, 0.3, (80, 3)), rng.normal(-5, 0.3, (5, 3))])
    labels = clusters(f)
    assert (labels == clusters(f)).all()
    # two big groups; the 5 stragglers (fewer than min_members) joined the nearest
    assert len(np.unique(labels)) == 2
    assert len(np.unique(labels[:100])) == 1 and len(np.unique(labels[100:180])) == 1
    assert labels[0] != labels[100]
    assert len(clusters(np.zeros((0, 3)))) == 0


def test_clusters_do_not_depend_on_one_k_means_run():
    # five overlapping groups of unequal sizes (4 units apart, spread 0.7): one k-means++ run lands
    # in a poor local optimum for some seeds (3 or 4 groups found); the tightest of the restarts not
    rng = np.random.default_rng(0)
    centres = rng.normal(size=(5, 5))
    centres *= 4.0 / np.linalg.norm(centres, axis=1, keepdims=True)
    sizes = [2000, 1200, 600, 300, 150]
    f = np.concatenate([c + 0.7 * rng.normal(size=(s, 5)) for c, s in zip(centres, sizes, strict=True)])
    truth = np.repeat(np.arange(5), sizes)
    for seed in range(8):
        labels = clusters(f, seed=seed)
        assert labels.max() + 1 == 5, seed
        purity = sum(np.bincount(truth[labels == j]).max() for j in range(5)) / len(f)
        assert purity > 0.99, (seed, purity)


def test_lobe_materials_are_their_members_medians():
    rho_d, alpha, rho_s = _two_materials(np.random.default_rng(1))
    m = lobe_clusters(rho_d, alpha, rho_s)[0]
    assert len(m) == 2
    order = np.argsort(m.alpha[:, 0])
    np.testing.assert_allclose(m.alpha[order], [[0.05, 0.05], [0.3, 0.05]], rtol=0.05)
    np.testing.assert_allclose(m.rho_s[order].mean(1), [3.0, 1.0], rtol=0.05)
    np.testing.assert_allclose(m.share.sum(), 1 - TUNING.materials.matte_share)
    back = BasisMaterials.from_arrays(m.to_arrays())
    for a, b in zip(back.to_arrays().values(), m.to_arrays().values(), strict=True):
        np.testing.assert_array_equal(a, b)
    assert len(lobe_clusters(rho_d[:3], alpha[:3], rho_s[:3])[0]) == 0  # too few to be a material
    # metal-strong lobes that never made much of a pixel (corrections to a bright diffuse) make no
    # material; a dielectric's lobe (the grey, rho_s 1) is faint by nature and makes one
    faint = np.full(400, 0.1)
    only = lobe_clusters(rho_d, alpha, rho_s, faint)[0]
    assert len(only) == 1
    np.testing.assert_allclose(only.rho_d[0], np.median(rho_d[200:], 0))


def test_lobe_clusters_name_each_texels_material():
    rho_d, alpha, rho_s = _two_materials(np.random.default_rng(1))
    m, members = lobe_clusters(rho_d, alpha, rho_s, np.r_[np.ones(200), np.full(200, 0.1)])
    assert len(m) == 2 and members.shape == (400,)
    assert len(set(members[:200])) == 1 and len(set(members[200:])) == 1 and members[0] != members[200]
    np.testing.assert_allclose(m.alpha[members[0]], np.median(alpha[:200], 0))
    # the blue's metal-strong lobes never showed themselves: no material, its texels in none
    faint = np.full(400, 0.1)
    only, members = lobe_clusters(rho_d, alpha, rho_s, faint)
    assert len(only) == 1 and (members[:200] == -1).all() and (members[200:] == 0).all()


def test_pooled_scale_takes_the_width_most_texels_prefer():
    """Each texel's cost over the width scales is its vote, clipped: 200 texels that prefer x2 by a
    little outvote 10 that fit no width well and pull hard toward x0.5 — where the plain sum of
    costs follows the 10. The minimum lies between grid points (the parabola finds it)."""
    scales = 2.0 ** np.linspace(-2, 2, 17)
    x = np.log2(scales)
    many = np.tile(0.8 * (x - np.log2(2.1)) ** 2, (200, 1)) + 3.0  # 3: each texel's own noise floor
    few = np.tile(400 * (x + 1) ** 2, (10, 1))
    costs = np.concatenate([many, few, np.full((1, 17), np.inf)])  # a texel no width fits: no vote
    assert abs(np.log2(pooled_scale(costs, scales)) - np.log2(2.1)) < 0.05
    assert pooled_scale(costs, scales, clip=np.inf) < 0.6  # the plain sum: the 10 decide
    assert pooled_scale(np.full((3, 17), np.inf), scales) == 1.0


def test_pooled_votes_count_each_texel_above_its_own_best_clipped():
    """Two candidates, four texels: one prefers the first by 0.5, one the second by 5 (its vote
    clipped at 2), one is inf under the second (a full vote against it), one inf under both (none)."""
    costs = np.array([[1.0, 1.5], [9.0, 4.0], [3.0, np.inf], [np.inf, np.inf]])
    np.testing.assert_allclose(pooled_votes(costs), [2.0, 0.5 + 2.0])
    np.testing.assert_allclose(pooled_votes(costs, clip=10.0), [5.0, 0.5 + 10.0])


def test_the_second_lobe_wins_only_where_each_member_pays_for_its_own_parameter():
    """100 members each explained better by the second candidate by 0.5 (half chi-square units):
    free, or paying 2 once, it wins (50 votes to 0); paying 1 per member (its own tangent) it loses,
    0.5 below what it costs each. By 3 each it wins either way; a member inf under the second is a
    full vote against it."""
    better = np.stack([np.full(100, 10.5), np.full(100, 10.0)], 1)
    assert second_wins(better) and second_wins(better, shared=2.0)
    assert not second_wins(better, shared=1.0, each=1.0)
    clearly = better - np.array([0.0, 2.5])
    assert second_wins(clearly, shared=1.0, each=1.0)
    one_against = np.concatenate([clearly, [[1.0, np.inf]]])
    assert second_wins(one_against, shared=1.0, each=1.0)  # votes 200 against 2 (+ 1)
    assert not second_wins(one_against[-2:], shared=1.0, each=1.0)  # one for, one against: 2 against 2 (+ 1)


def test_a_cluster_counts_as_a_material_by_how_many_of_its_lobes_showed_themselves():
    rho_d, alpha, rho_s = _two_materials(np.random.default_rng(2))  # blue: rho_s 3, grey: rho_s 1

    def shares(frac_blue: float) -> np.ndarray:
        """The two materials' shares (blue, grey) when that share of the blue's lobes (metal-strong)
        made a highlight; none of the grey's (a dielectric's: rho_s 1) did."""
        hl = np.r_[np.where(np.arange(200) < frac_blue * 200, 0.9, 0.1), np.full(200, 0.1)]
        m = lobe_clusters(rho_d, alpha, rho_s, hl)[0]
        out = np.zeros(2)
        out[(m.alpha[:, 0] > 0.1).astype(int)] = m.share  # blue alpha 0.05, grey 0.3
        return out

    full = (1 - TUNING.materials.matte_share) / 2
    np.testing.assert_allclose(shares(1), [full, full])
    # by degree: the weight is members x f^2, f the share of them that showed themselves
    np.testing.assert_allclose(shares(0.5), [full / 4, full])
    faint, metal, dielectric = np.full((100, 3), 5.0), np.r_[np.full(30, 0.9), np.full(70, 0.1)], np.ones((100, 3))
    assert material_weight(metal, faint) == 100 * 0.3**2
    assert material_weight(metal, dielectric) == 100
    assert material_weight(metal[:0], faint[:0]) == 0
    # no step at a median of min_highlight: 49% and 51% of the lobes highlighted weigh nearly the same
    lo, hi = shares(0.49)[0], shares(0.51)[0]
    assert 0 < lo < hi < 1.1 * lo
    # a cluster few of whose lobes showed themselves (weighing under min_members texels) is none
    assert shares(0)[0] == 0 and shares(0.25)[0] == 0  # 200 x 0.25^2 = 12.5 < 16
    assert shares(0.3)[0] > 0  # 18


def test_class_costs_follow_colour_and_share():
    rho_d, alpha, rho_s = _two_materials(np.random.default_rng(3))
    m = lobe_clusters(rho_d, alpha, rho_s)[0]
    blue = int(np.argmin(m.alpha[:, 0]))
    probe = np.array([[0.05, 0.08, 0.3], [0.2, 0.2, 0.2], [0.9, 0.1, 0.05]])  # blue, grey, a red no material has
    c = class_costs(probe, m)
    assert c.shape == (3, 3)
    assert np.argmin(c[0]) == 1 + blue  # a trace that cannot tell: its colour's lobe material
    assert np.argmin(c[1]) == 2 - blue
    assert np.argmin(c[2]) == 0  # red: the broad matte class, by far
    assert c[2, 1:].min() - c[2, 0] > 10
    # only the materials of a texel's colour are worth its trace's judgement, and the broad ones
    cand = candidates(c, m)
    assert cand.shape == (3, 2) and cand[0, blue] and not cand[0, 1 - blue] and cand[1, 1 - blue]
    broad = dataclasses.replace(m, alpha=np.where(np.arange(2)[:, None] == 1 - blue, 0.3, m.alpha))
    assert candidates(class_costs(probe, broad), broad)[:, 1 - blue].all()
    assert class_costs(probe, BasisMaterials.empty()).shape == (3, 1)
    assert candidates(class_costs(probe, BasisMaterials.empty()), BasisMaterials.empty()).shape == (3, 0)


def test_a_texel_judged_under_a_lobe_is_coloured_as_under_it():
    """A broad lobe's members answered 0.16 by their own (narrower) lobes, 0.05 under the material's
    pooled one (``lobe_rho_d``); a texel judged without a lobe at 0.16 re-solves to 0.05 under it:
    that is the colour held to the material's under the same lobe — a perfect match, where against
    the members' own answers it would be far off. A material not judged for a texel (NaN) holds the
    texel's rho_d without a lobe to its colour under its lobe."""
    rho_d, alpha, rho_s = _two_materials(np.random.default_rng(3))
    m = lobe_clusters(rho_d, alpha, rho_s)[0]
    np.testing.assert_allclose(m.lobe_rho_d, m.rho_d)  # until the widths are pooled
    grey = int(np.argmax(m.alpha[:, 0]))
    m.rho_d[grey], m.lobe_rho_d[grey] = 0.16, 0.05
    judged = np.full((2, 3, 3), np.nan)
    judged[:, 0] = 0.16  # without a lobe
    judged[0, 1 + grey] = 0.05  # under the grey material's lobe
    c = judged_colour_costs(judged, m)
    assert c.shape == (2, 3) and np.isfinite(c).all()
    shares = np.log(np.concatenate([[TUNING.materials.matte_share], m.share]))
    np.testing.assert_allclose(c[:, 0], class_costs(judged[:1, 0], m)[0, 0] + shares[0])
    np.testing.assert_allclose(c[0, 1 + grey], 3 * np.log(m.colour_sigma[grey]))  # its colour exactly
    assert class_costs(judged[:1, 1 + grey], m)[0, 1 + grey] + shares[1 + grey] > c[0, 1 + grey] + 10
    under = dataclasses.replace(m, rho_d=m.lobe_rho_d)
    np.testing.assert_allclose(c[1, 1:], class_costs(judged[1:, 0], under)[0, 1:] + shares[1:])


def test_the_matte_share_is_the_objects_own():
    one = BasisMaterials(
        np.full((1, 3), 0.2),
        np.full((1, 2), 0.1),
        np.ones((1, 3)),
        np.full(1, 0.1),
        np.full(1, 0.25),
        np.full(1, 0.25),
        np.array([1 - TUNING.materials.matte_share]),
        np.full((1, 3), 0.2),
    )
    # 30% of the texels' traces say matte, 20% kept a lobe of their own, half cannot tell: the
    # likeliest share is 0.3 / 0.5 (those that cannot tell follow the prior, whatever it is)
    costs = np.concatenate([np.tile([0.0, 10.0], (300, 1)), np.tile([np.inf, 0.0], (200, 1)), np.zeros((500, 2))])
    assert abs(estimated_matte_share(costs, one) - 0.6) < 0.01
    # a glossy object whose texels never say matte: the share falls to its floor, not 0
    assert estimated_matte_share(costs[300:], one) == TUNING.materials.matte_share_range[0]
    assert estimated_matte_share(costs[:300], one) == TUNING.materials.matte_share_range[1]
    assert estimated_matte_share(np.full((4, 2), np.inf), one) == TUNING.materials.matte_share  # nobody could be either
    # a lower matte share moves a texel that cannot tell to its colour's lobe material
    grey = np.array([[0.2, 0.2, 0.2]])
    assert np.argmin(class_costs(grey, one)[0]) == 1
    far = np.array([[0.265, 0.265, 0.265]])  # 2.5 sigma off the material's colour
    assert np.argmin(class_costs(far, one, 0.5)[0]) == 0 and np.argmin(class_costs(far, one, 0.05)[0]) == 1


def test_a_cluster_whose_colour_another_material_holds_is_none():
    rng = np.random.default_rng(5)
    rho_d, alpha, rho_s = _two_materials(rng)
    # a third cluster: the grey material's colour, its lobe read isotropic and sharp (one LED)
    n = 60
    sharp_d = np.tile([0.2, 0.2, 0.2], (n, 1)) * np.exp(0.05 * rng.standard_normal((n, 3)))
    sharp_a = np.full((n, 2), 0.008) * np.exp(0.05 * rng.standard_normal((n, 2)))
    rho_d, alpha = np.concatenate([rho_d, sharp_d]), np.concatenate([alpha, sharp_a])
    rho_s = np.concatenate([rho_s, np.full((n, 3), 1.0)])
    m, members = lobe_clusters(rho_d, alpha, rho_s)
    assert len(m) == 3  # by the features: three materials
    held, renumbered = colour_held(m, members, rho_d)
    # by colour its members fall to the grey material with the larger share: two materials hold texels
    assert len(held) == 2
    assert sorted(np.round(held.alpha[:, 0], 2)) == sorted(np.round(m.alpha[m.share > m.share.min(), 0], 2))
    sharp = int(np.argmin(m.share))
    assert (renumbered[members == sharp] == -1).all()
    assert (renumbered >= 0).sum() == (members != sharp).sum()
    kept = renumbered >= 0
    assert np.allclose(held.alpha[renumbered[kept]], m.alpha[members[kept]])
    # none to hold: as given
    empty, none = colour_held(BasisMaterials.empty(), np.full(4, -1), rho_d[:4])
    assert len(empty) == 0 and (none == -1).all()


def _votes_at(preferred: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """Costs ``(n, S)`` of members whose traces prefer the scales ``preferred (n,)``: a parabola in
    log scale (4 half chi-square units per octave squared)."""
    return 4.0 * (np.log2(scales)[None] - np.log2(preferred)[:, None]) ** 2


def test_best_scales_is_pooled_scales_minimum_row_by_row():
    from ntp_engine.refine.materials import best_scales, pooled_scale, pooled_votes

    scales = 2.0 ** np.linspace(-2, 2, 9)
    rng = np.random.default_rng(3)
    for preferred in (0.6, 1.0, 1.7, 3.9, 5.0):
        costs = _votes_at(preferred * np.exp(0.1 * rng.standard_normal(20)), scales)
        got = best_scales(pooled_votes(costs)[None], scales)[0]
        assert got == pytest.approx(pooled_scale(costs, scales))
        assert got == pytest.approx(np.clip(preferred, 0.25, 4.0), rel=0.12)


def test_a_width_that_varies_over_the_object_becomes_a_field_and_a_constant_one_does_not():
    """Members along a 10 cm strip whose traces prefer a width running 0.02 -> 0.25 along it (the
    gallery dome's lacquer): the field's width at a point is the one its neighbours prefer (within
    12%), where one width for all is 3.5x off at the ends. Members that all prefer one width (with
    noise): no field."""
    from ntp_engine.refine.materials import width_field

    scales = 2.0 ** np.linspace(-2, 2, 9)
    alpha = np.array([0.07, 0.07])
    rng = np.random.default_rng(5)
    n = 256
    x = np.sort(rng.uniform(0, 0.1, n))
    position = np.stack([x, 0.01 * rng.standard_normal(n), np.zeros(n)], 1)
    truth = np.exp(np.log(0.02) + (np.log(0.25) - np.log(0.02)) * x / 0.1)
    noise = np.exp(0.15 * rng.standard_normal(n))
    field = width_field(_votes_at(truth * noise / 0.07, scales), position, alpha, scales)
    assert field is not None
    probe = np.array([[0.01, 0.0, 0.0], [0.05, 0.0, 0.0], [0.09, 0.0, 0.0]])
    expected = np.exp(np.log(0.02) + (np.log(0.25) - np.log(0.02)) * probe[:, 0] / 0.1)
    got = field.at(probe)
    np.testing.assert_allclose(got[:, 0], expected, rtol=0.12)
    np.testing.assert_allclose(got[:, 0], got[:, 1])
    assert width_field(_votes_at(1.3 * noise, scales), position, alpha, scales) is None


def test_local_shares_are_the_neighbours_classes_with_the_objects_as_more():
    """A plane of texels, matte on the left and material 1 on the right: far from the border a
    texel's shares are its side's class by ``label_neighbours`` to the object's ``share_pseudo``;
    at the border both; a lone texel has the object's shares."""
    x, y = np.meshgrid(np.arange(20.0), np.arange(20.0))
    position = np.stack([x.ravel(), y.ravel(), np.zeros(400)], 1) * 1e-3
    label = np.where(x.ravel() < 10, -1, 1)
    shares = np.array([0.5, 0.2, 0.3])
    local = local_shares(label_neighbours(position), label, shares)
    assert local.shape == (400, 3)
    np.testing.assert_allclose(local.sum(1), 1.0)
    base, total = (
        TUNING.materials.share_pseudo * shares,
        TUNING.materials.label_neighbours + TUNING.materials.share_pseudo,
    )
    far_left, far_right = 10 * 20 + 0, 10 * 20 + 19
    np.testing.assert_allclose(local[far_left], (base + [TUNING.materials.label_neighbours, 0, 0]) / total)
    np.testing.assert_allclose(local[far_right], (base + [0, 0, TUNING.materials.label_neighbours]) / total)
    border = 10 * 20 + 9  # last matte column: about half its neighbours are material 1
    assert 0.3 < local[border, 0] < 0.7 and 0.3 < local[border, 2] < 0.7
    np.testing.assert_allclose(local_shares(label_neighbours(position[:1]), label[:1], shares), [shares / shares.sum()])
