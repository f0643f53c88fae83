"""Basis materials: most objects are made of a few materials (Lensch et al. 2003; Nam et al. 2018),
so a texel whose own trace does not constrain its lobe takes it from the material it belongs to.

The lobe materials come from the texels that are informative about a lobe: k-means clusters of the
texels whose own trace kept one (``refine``'s evidence test), in (log rho_d, log alpha, log rho_s)
scaled so that one unit is a difference worth telling materials apart by. Besides them, one broad
matte class: no lobe, any colour. A texel is assigned by its trace and its colour together (a
mixture model): the data cost of its trace under each material's lobe or none
(``refine.material_costs``), plus the colour's cost — a lobe material's Gaussian in log rho_d with its
members' spread, the matte class's a broad one — minus the log of the class's share. So a texel
whose trace cannot tell (its entries miss the lobe) joins the lobe material of its colour, one of
another colour stays matte, and where the trace tells, it decides. Its colour under a material is
its rho_d re-solved under that material's lobe, held to the members' rho_d under the same lobe
(``judged_colour_costs``): a broad lobe's light looks diffuse, and judged without it a rough metal
is as bright as its lobe makes it (the gallery's knot: ρd 0.16 for 0.05, taken for matte). A
texel's trace judges the lobe materials within ``TUNING.materials.candidate_margin`` of its likeliest by that
colour, and every broad one (``TUNING.materials.broad_alpha``), whose colour it cannot know before. The matte
class's share is the object's own (``estimated_matte_share``: the mixture's maximum likelihood,
by EM from ``TUNING.materials.matte_share``): an object with little matte surface gives a texel that cannot tell
to its colour's lobe material, one with much keeps it matte. Then each class's share where the
texel lies (``local_shares``: its nearest texels' labels, the object's shares counting as a few
more): materials come in regions, and a texel among matte ones that its trace cannot tell stays
matte whatever its colour.

A material's lobe width is then what its members' traces explain best together
(``pooled_scale`` over ``refine.lobe_costs``, in ``refine.material_pass.pooled_widths``), not the
median of their own answers, which one trace often cannot pin down.

Convention: rho_d, rho_s linear RGB ``(N, 3)``; alpha ``(N, 2)`` with alpha_x >= alpha_y (the
refinement's canonical lobe); costs in half chi-square units like the refinement's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.cluster.vq import kmeans2
from scipy.spatial import cKDTree

from ..physics.brdf import ALPHA_MAX, ALPHA_MIN
from .settings import TUNING


@dataclass(frozen=True)
class BasisMaterials:
    """K lobe materials: medians and spreads of their members, and their shares."""

    rho_d: np.ndarray  # (K, 3)
    alpha: np.ndarray  # (K, 2) alpha_x >= alpha_y
    rho_s: np.ndarray  # (K, 3)
    colour_sigma: np.ndarray  # (K,) of log(rho_d + TUNING.materials.colour_floor), per channel
    log_alpha_sigma: np.ndarray  # (K,)
    rho_s_sigma: np.ndarray  # (K,) linear units
    share: np.ndarray  # (K,) prior share: (1 - TUNING.materials.matte_share) x material_weight / all lobe texels
    # (K, 3) its members' rho_d under its own lobe (``rho_d`` is their own answers', whose lobes may be narrower)
    lobe_rho_d: np.ndarray
    # where a material's width varies over the object, its field (``width_field``; K entries or none)
    width: tuple[WidthField | None, ...] = ()

    def __len__(self) -> int:
        return len(self.share)

    @staticmethod
    def empty() -> BasisMaterials:
        """No materials (K = 0)."""
        z2, z1 = np.zeros((0, 3)), np.zeros(0)
        return BasisMaterials(z2, np.zeros((0, 2)), z2, z1, z1, z1, z1, z2)

    def to_arrays(self, prefix: str = "material_") -> dict[str, np.ndarray]:
        """Flat arrays for an ``.npz`` (``from_arrays`` reads them back)."""
        return {prefix + k: v for k, v in zip(_NAMES, _fields(self), strict=True)}

    @staticmethod
    def from_arrays(z: dict[str, np.ndarray], prefix: str = "material_") -> BasisMaterials:
        """The materials ``to_arrays`` wrote."""
        return _materials([np.asarray(z[prefix + k]) for k in _NAMES])

    def alpha_at(self, material: np.ndarray, position: np.ndarray | None) -> np.ndarray:
        """The lobe width ``(T, 2)`` of texels in lobe materials ``material (T,)`` at ``position (T,
        3)``: their material's, or its field's there (``width``; without positions, the material's)."""
        alpha = self.alpha[material]
        for k, field in enumerate(self.width):
            here = material == k
            if field is not None and position is not None and here.any():
                alpha[here] = field.at(position[here])
        return alpha

    def subset(self, keep: np.ndarray) -> BasisMaterials:
        """The materials ``keep`` (bool ``(K,)`` or indices), in order."""
        width = tuple(np.asarray(self.width, object)[keep]) if self.width else ()
        return _materials([v[keep] for v in _fields(self)], width)


_NAMES = ("rho_d", "alpha", "rho_s", "colour_sigma", "log_alpha_sigma", "rho_s_sigma", "share", "lobe_rho_d")


def _materials(values: list[np.ndarray], width: tuple[WidthField | None, ...] = ()) -> BasisMaterials:
    """``BasisMaterials`` of its arrays in ``_NAMES``' order."""
    rho_d, alpha, rho_s, colour_sigma, log_alpha_sigma, rho_s_sigma, share, lobe_rho_d = values
    return BasisMaterials(rho_d, alpha, rho_s, colour_sigma, log_alpha_sigma, rho_s_sigma, share, lobe_rho_d, width)


def _fields(m: BasisMaterials) -> tuple[np.ndarray, ...]:
    return tuple(getattr(m, k) for k in _NAMES)


def _log_colour(rho_d: np.ndarray) -> np.ndarray:
    return np.log(np.clip(rho_d, 0, None) + TUNING.materials.colour_floor)


def _mad(x: np.ndarray) -> float:
    """Robust standard deviation (1.4826 median absolute deviation) over all of ``x``."""
    return float(1.4826 * np.median(np.abs(x - np.median(x, 0)))) if len(x) else 0.0


def clusters(features: np.ndarray, max_k: int = TUNING.materials.max_materials, seed: int = 0) -> np.ndarray:
    """Labels ``(n,)`` of k-means clusters of ``features (n, d)`` (units of equal weight): the most
    clusters, up to ``max_k``, whose centres all lie ``TUNING.materials.separation`` units apart, once clusters smaller
    than ``TUNING.materials.min_members`` (or ``TUNING.materials.min_share``) have joined their nearest larger
    one. (A likelihood
    criterion such as BIC splits any Gaussian blob under hard assignments; the feature units say
    what difference makes another material.) Each k keeps the tightest of ``TUNING.materials.restarts`` k-means runs.
    Deterministic."""
    n = len(features)
    best = np.zeros(n, np.int64)
    for k in range(2, min(max_k, n) + 1):
        labels = _tightest_kmeans(features, k, seed + TUNING.materials.restarts * k)
        labels = _merge_small(features, labels)
        centres = np.stack([features[labels == j].mean(0) for j in range(int(labels.max()) + 1)])
        gaps = (
            np.sqrt(((centres[:, None] - centres[None]) ** 2).sum(-1))
            + np.eye(len(centres)) * TUNING.materials.separation
        )
        if len(centres) > int(best.max(initial=0)) + 1 and gaps.min() >= TUNING.materials.separation:
            best = labels
    return best


def _tightest_kmeans(features: np.ndarray, k: int, seed: int) -> np.ndarray:
    """Labels of the k-means++ run, of ``TUNING.materials.restarts`` seeded ones, with the least within-cluster sum of
    squares. (With one run the demo's first pass gave 5 or 6 clusters depending on float32 rounding:
    the run's local optimum decided, not the data.)"""
    best_ss, best = np.inf, np.zeros(len(features), np.int64)
    for r in range(TUNING.materials.restarts):
        centres, labels = kmeans2(features, k, minit="++", seed=seed + r)
        ss = float(((features - centres[labels]) ** 2).sum())
        if ss < best_ss:
            best_ss, best = ss, labels
    return best


def _merge_small(features: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """``labels`` with clusters below ``TUNING.materials.min_members`` (or ``TUNING.materials.min_share``) joined
    to the nearest big
    one (by centre), renumbered 0..K-1."""
    ids, counts = np.unique(labels, return_counts=True)
    big = ids[(counts >= TUNING.materials.min_members) & (counts >= TUNING.materials.min_share * len(labels))]
    if len(big) == 0:
        return np.zeros(len(labels), np.int64)
    centres = np.stack([features[labels == k].mean(0) for k in big])
    nearest = big[np.argmin(((features[:, None] - centres[None]) ** 2).sum(-1), 1)]
    return np.unique(np.where(np.isin(labels, big), labels, nearest), return_inverse=True)[1]


def material_weight(highlight: np.ndarray, rho_s: np.ndarray) -> float:
    """How many texels a cluster counts as, from its members' ``highlight (m,)`` and ``rho_s (m, 3)``.
    A member's lobe *showed itself* if it made ``TUNING.materials.min_highlight`` or more of some pixel, or is of
    dielectric strength (mean rho_s <= ``TUNING.materials.dielectric_rho_s``: such a lobe makes a small share of a
    pixel over a diffuse unless it is sharp, the rough plastics' 12-15%; the spurious lobes that fit
    blended or shadowed pixels are metal-strong, rho_s 5-10). With f the share of members whose lobe
    showed itself, the weight is m f^2: those members (m f), weighed by how likely the cluster is a
    material at all (f). It moves smoothly as the members' lobes do: a yes-or-no rule on the median
    highlight flipped whole materials in or out when a scan's lobes moved a little (docs/history/accuracy.md)."""
    if len(highlight) == 0:
        return 0.0
    f = float(
        ((highlight >= TUNING.materials.min_highlight) | (rho_s.mean(1) <= TUNING.materials.dielectric_rho_s)).mean()
    )
    return len(highlight) * f * f


def lobe_clusters(
    rho_d: np.ndarray, alpha: np.ndarray, rho_s: np.ndarray, highlight: np.ndarray | None = None
) -> tuple[BasisMaterials, np.ndarray]:
    """Lobe materials from the texels whose own trace kept a lobe: their rho_d, alpha, rho_s
    ``(n, 3), (n, 2), (n, 3)`` and ``highlight (n,)`` (the largest share of a pixel their lobe made,
    ``refine.Refined.highlight``; default 1). A cluster most of whose lobes are small metal-strong
    corrections to a bright diffuse (pixels that blend two albedos, shadow edges) is no material;
    one whose lobes showed themselves is. Between the two, a cluster counts by degree (``material_weight``):
    its prior share is (1 - ``TUNING.materials.matte_share``) x weight / n, and under
    ``TUNING.materials.min_members`` of weight
    it is none. Also returns each texel's material ``(n,)`` (-1: in no material)."""
    members = np.full(len(rho_d), -1, np.int64)
    if len(rho_d) < TUNING.materials.min_members:
        return BasisMaterials.empty(), members
    f = np.concatenate(
        [
            _log_colour(rho_d) / TUNING.materials.colour_scale,
            np.log(alpha) / TUNING.materials.log_alpha_scale,
            np.log(np.maximum(rho_s.mean(1, keepdims=True), 1e-3)) / TUNING.materials.log_rho_s_scale,
        ],
        1,
    )
    labels = clusters(f)
    highlight = np.ones(len(rho_d)) if highlight is None else highlight
    rows: list[tuple] = []
    for k in range(int(labels.max()) + 1):
        m = labels == k
        weight = material_weight(highlight[m], rho_s[m])
        if weight < TUNING.materials.min_members:
            continue
        members[m] = len(rows)
        la, rs = np.log(alpha[m]), rho_s[m]
        rs_mean = float(np.median(rs.mean(1)))
        rows.append(
            (
                np.median(rho_d[m], 0),
                np.exp(np.median(la, 0)),
                np.median(rs, 0),
                max(_mad(_log_colour(rho_d[m])), TUNING.materials.min_colour_sigma),
                max(_mad(la), TUNING.materials.min_log_alpha_sigma),
                max(_mad(rs.mean(1)), TUNING.materials.min_rho_s_sigma * rs_mean),
                (1 - TUNING.materials.matte_share) * weight / len(rho_d),
                np.median(rho_d[m], 0),
            )
        )
    if not rows:
        return BasisMaterials.empty(), members
    return _materials([np.array([r[i] for r in rows]) for i in range(len(_NAMES))]), members


def pooled_votes(costs: np.ndarray, clip: float = TUNING.materials.pool_clip) -> np.ndarray:
    """The candidates' totals ``(S,)`` of ``costs (n, S)`` (n texels' traces under S candidate
    lobes): each texel's costs above its own best, clipped at ``clip``, summed; the lowest total is
    what the texels together favour. Texels whose every cost is inf do not vote."""
    return clipped_votes(costs, clip).sum(0)


def second_wins(
    costs: np.ndarray, shared: float = 0.0, each: float = 0.0, clip: float = TUNING.materials.pool_clip
) -> bool:
    """Whether a material's members' traces, together, choose the second of two candidate lobes:
    ``costs (n, 2)`` of each member's trace under both (``refine.lobe_costs``), votes clipped as in
    ``pooled_votes``. The second pays for what it adds in half chi-square units, as AIC counts
    parameters: ``shared`` once (a parameter of the material's: an anisotropic lobe's alpha ratio)
    and ``each`` in every member's own vote (one per member: its tangent, which its own solve chose)."""
    votes = pooled_votes(costs + np.array([0.0, each]), clip)
    return bool(votes[1] + shared < votes[0])


def pooled_scale(costs: np.ndarray, scales: np.ndarray, clip: float = TUNING.materials.pool_clip) -> float:
    """The scale of a material's lobe width that its texels' traces, together, explain best:
    ``costs (n, S)`` of each texel's trace under the lobe at ``scales (S,)`` (ascending,
    ``refine.lobe_costs``). Each texel's costs are taken above its own best and clipped at ``clip``
    before they are summed — a vote of bounded weight, so the few texels whose traces fit no width
    (blended or shadowed pixels) do not decide for the many that prefer one by a little (on the
    gallery's box the plain sum chose 0.30 for its alpha 0.5 metal, the clipped one 0.50). The
    minimum of the sum, refined by a parabola through its neighbours in log scale; texels whose
    every cost is inf do not vote."""
    if not np.isfinite(costs).any():
        return 1.0
    return float(best_scales(pooled_votes(costs, clip)[None], scales)[0])


def best_scales(totals: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """The scale ``(T,)`` at the minimum of each row of vote ``totals (T, S)`` over ``scales (S,)``
    (ascending), refined by a parabola through its neighbours in log scale (within half a step)."""
    T, S = totals.shape
    j = np.argmin(totals, 1)
    x = np.log(scales)
    inner = np.clip(j, 1, S - 2)
    y0, y1, y2 = (totals[np.arange(T), inner + d] for d in (-1, 0, 1))
    curve = y0 - 2 * y1 + y2
    ok = (j == inner) & (curve > 0)
    step = np.where(ok, 0.5 * (y0 - y2) / np.where(ok, curve, 1.0), 0.0)  # grid steps, within (-0.5, 0.5)
    return np.where(ok, np.exp(x[j] + step * (x[np.minimum(j + 1, S - 1)] - x[j])), scales[j])


def clipped_votes(costs: np.ndarray, clip: float = TUNING.materials.pool_clip) -> np.ndarray:
    """Each texel's vote ``(n, S)`` of ``costs (n, S)``: above its own best, clipped at ``clip``
    (``pooled_votes`` sums them); 0 where every cost is inf (no vote)."""
    live = np.isfinite(costs).any(1)
    votes = np.zeros(costs.shape)
    votes[live] = np.minimum(costs[live] - costs[live].min(1, keepdims=True), clip)
    return votes


def votes_at(votes: np.ndarray, scale: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """Each member's vote ``(n,)`` of ``votes (n, S)`` over ``scales (S,)`` (ascending, evenly
    spaced in log) at its own ``scale (n,)``: the parabola through the three grid votes nearest
    it, in log scale, at least 0 (linear interpolation overstates a smooth vote between grid
    points, and so favours answers that land on them)."""
    x = np.log(scales)
    step = x[1] - x[0]
    j = np.clip(np.rint((np.log(scale) - x[0]) / step).astype(int), 1, len(scales) - 2)
    t = (np.log(scale) - x[j]) / step
    rows = np.arange(len(votes))
    y0, y1, y2 = (votes[rows, j + d] for d in (-1, 0, 1))
    return np.maximum(y1 + 0.5 * t * (y2 - y0) + 0.5 * t * t * (y0 - 2 * y1 + y2), 0.0)


@dataclass(frozen=True)
class WidthField:
    """A lobe material's width where it varies over the object (``width_field``): the votes of its
    sampled members over scales of its pooled width, and where they lie. At a point, the width
    the ``TUNING.materials.local_members`` members nearest it vote for (``at``)."""

    position: np.ndarray  # (n, 3) the members' points (object space, metres)
    votes: np.ndarray  # (n, S) each member's clipped vote (``clipped_votes``)
    alpha: np.ndarray  # (2,) the pooled width (alpha_x >= alpha_y) the scales multiply
    scales: np.ndarray  # (S,) ascending

    def at(self, position: np.ndarray) -> np.ndarray:
        """Widths ``(T, 2)`` at points ``position (T, 3)``, clamped to ``[ALPHA_MIN, ALPHA_MAX]``."""
        k = min(TUNING.materials.local_members, len(self.position))
        _, near = cKDTree(self.position).query(position, k=k)
        near = near.reshape(len(position), k)
        scale = best_scales(self.votes[near].sum(1), self.scales)
        return np.clip(scale[:, None] * self.alpha[None], ALPHA_MIN, ALPHA_MAX)


def width_field(costs: np.ndarray, position: np.ndarray, alpha: np.ndarray, scales: np.ndarray) -> WidthField | None:
    """A material's width as a field over the object, or None where one width serves it: ``costs
    (n, S)`` of its sampled members' traces under its lobe ``alpha (2,)`` times ``scales (S,)``
    (``refine.lobe_costs``), the members at ``position (n, 3)``. Left-one-out: each member's vote at
    the width its ``TUNING.materials.local_members`` nearest others choose, summed, against the same at the width all
    the others choose — the field where its neighbours predict the members better by ``TUNING.materials.field_units``
    per neighbourhood (the gallery's dome: its lacquer's alpha runs 0.01 to 0.25
    around it, 47 against 91 for 8 neighbourhoods).
    Members without a vote (every cost inf) are left out."""
    live = np.isfinite(costs).any(1)
    votes, position = clipped_votes(costs[live]), position[live]
    n = len(votes)
    if n <= TUNING.materials.local_members:
        return None

    def held_out(scale: np.ndarray) -> float:  # each member's vote at the scale chosen without it
        return float(votes_at(votes, scale, scales).sum())

    everyone = best_scales(votes.sum(0)[None] - votes, scales)
    _, near = cKDTree(position).query(position, k=TUNING.materials.local_members + 1)
    others = np.where(near[:, :1] == np.arange(n)[:, None], near[:, 1:], near[:, :-1])  # itself left out
    local = best_scales(votes[others].sum(1), scales)
    # the field pays TUNING.materials.field_units per neighbourhood it could set on its own: the left-out votes
    # alone favoured it by 1% where every member preferred one width (test_materials), and on the
    # engine gallery's materials of one width by 8-24 for 8 neighbourhoods (the box's alpha 0.5
    # metal 23.2 against 31.3, the vase's 0.006 lacquer 172 against 196, the knot's 0.02 plastic
    # 169 against 190: what the model misses varies over an object too); the dome's lacquer, whose
    # width varies, by 44 and 52 (its two clusters)
    if held_out(local) + TUNING.materials.field_units * n / TUNING.materials.local_members >= held_out(everyone):
        return None
    return WidthField(position, votes, np.asarray(alpha, float), np.asarray(scales, float))


def _colour_costs(rho_d: np.ndarray, centre: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Negative log density ``(N, K)`` of each texel's log(rho_d + TUNING.materials.colour_floor) under each of K
    materials' colours ``centre (K, 3)`` with spreads ``sigma (K,)``: ``rho_d (N, 3)`` held to every
    material, or ``(N, K, 3)`` one per material."""
    rho_d = rho_d[:, None] if rho_d.ndim == 2 else rho_d
    z = (_log_colour(rho_d) - _log_colour(centre)[None]) / sigma[None, :, None]
    return 0.5 * (z**2).sum(-1) + 3 * np.log(sigma)[None]


# the broad matte class's colour cost, at its expected value (any colour being as likely)
_BROAD_COLOUR = 1.5 + 3 * math.log(TUNING.materials.matte_colour_sigma)


def colour_costs(rho_d: np.ndarray, materials: BasisMaterials) -> np.ndarray:
    """Negative log density ``(N, 1 + K)`` of each texel's ``rho_d (N, 3)`` under the broad matte
    class (column 0) and each lobe material, without the classes' shares."""
    lobe = _colour_costs(rho_d, materials.rho_d, materials.colour_sigma)
    return np.concatenate([np.full((len(rho_d), 1), _BROAD_COLOUR), lobe], 1)


def judged_colour_costs(rho_d: np.ndarray, materials: BasisMaterials) -> np.ndarray:
    """``colour_costs`` ``(N, 1 + K)`` of each texel's rho_d under each model ``rho_d (N, 1 + K, 3)``
    (no lobe, then each lobe material's; ``refine.policy.material_costs``): a texel's rho_d is only
    defined with its lobe, and a broad lobe's light looks diffuse — a rough metal judged without its
    lobe is as bright as its lobe makes it. Where a material was not judged (NaN), the rho_d without
    a lobe stands in."""
    own = np.where(np.isnan(rho_d[:, 1:]), rho_d[:, :1], rho_d[:, 1:])  # (N, K, 3)
    lobe = _colour_costs(own, materials.lobe_rho_d, materials.colour_sigma)  # the members' colour under the same lobe
    return np.concatenate([np.full((len(rho_d), 1), _BROAD_COLOUR), lobe], 1)


def class_shares(materials: BasisMaterials, matte_share: float = TUNING.materials.matte_share) -> np.ndarray:
    """Prior shares ``(1 + K,)``: the matte class's, then the lobe materials' — theirs
    (``materials.share``, made at ``TUNING.materials.matte_share``) scaled to the rest, (1 - matte_share) / (1 -
    ``TUNING.materials.matte_share``); they need not sum to 1 (a cluster that is no material keeps its part)."""
    return np.concatenate([[matte_share], materials.share * ((1 - matte_share) / (1 - TUNING.materials.matte_share))])


def label_neighbours(position: np.ndarray) -> np.ndarray:
    """The ``TUNING.materials.label_neighbours`` nearest other texels of each texel at ``position (N, 3)``: indices
    ``(N, k)``, k = min(TUNING.materials.label_neighbours, N - 1) (``local_shares``' neighbourhoods, fixed while the
    labels change)."""
    if len(position) < 2:
        return np.zeros((len(position), 0), np.int64)
    k = min(TUNING.materials.label_neighbours + 1, len(position))
    return cKDTree(position).query(position, k=k)[1][:, 1:]  # the texel itself first: left out


def local_shares(near: np.ndarray, label: np.ndarray, shares: np.ndarray) -> np.ndarray:
    """Each texel's class shares ``(N, 1 + K)`` where it lies: the labels ``label (N,)`` (-1 matte,
    0..K-1 the lobe materials) of its neighbours ``near (N, k)`` (``label_neighbours``) counted with
    the object's ``shares (1 + K,)`` (``class_shares``) as ``TUNING.materials.share_pseudo`` more, then normalised.
    Most objects are made of a few materials in regions: a texel whose own trace cannot tell takes
    the class its neighbours have (the vase's black print cells, 3 entries each, joined the dark
    metal by colour among white, matte ones)."""
    N, k = near.shape
    counts = np.zeros((N, len(shares)))
    np.add.at(counts, (np.repeat(np.arange(N), k), (label[near] + 1).ravel()), 1.0)
    out = counts + TUNING.materials.share_pseudo * shares / shares.sum()
    return out / out.sum(1, keepdims=True)


def class_costs(
    rho_d: np.ndarray, materials: BasisMaterials, matte_share: float = TUNING.materials.matte_share
) -> np.ndarray:
    """Prior cost ``(N, 1 + K)`` of each texel's ``rho_d (N, 3)`` under the broad matte class
    (column 0) and each lobe material: the colour's negative log density minus the log of the
    class's share (``class_shares``)."""
    return colour_costs(rho_d, materials) - np.log(class_shares(materials, matte_share))[None]


def estimated_matte_share(costs: np.ndarray, materials: BasisMaterials) -> float:
    """The matte class's share that makes the texels' ``costs (N, 1 + K)`` likeliest — each texel's
    negative log likelihood under matte (column 0) and each lobe material without the shares (its
    colour, plus its trace's cost where judged; inf: ruled out) — with the lobe materials' relative
    shares kept (``class_shares``). EM from ``TUNING.materials.matte_share``: a share is the mean of the texels'
    posteriors under it. Clipped to ``TUNING.materials.matte_share_range``; ``TUNING.materials.matte_share``
    without a texel that
    could be either."""
    c = costs[np.isfinite(costs).any(1)]
    if len(c) == 0:
        return TUNING.materials.matte_share
    c = np.exp(-(c - c.min(1, keepdims=True)))  # likelihoods, each row's best 1
    matte, lobe = c[:, 0], c[:, 1:] @ class_shares(materials, 0.0)[1:]
    share = TUNING.materials.matte_share
    for _ in range(TUNING.materials.share_em_iterations):
        posterior = share * matte / np.maximum(share * matte + (1 - share) * lobe, 1e-300)
        new = float(posterior.mean())
        done = abs(new - share) < TUNING.materials.share_em_tolerance
        share = new
        if done:
            break
    return float(np.clip(share, *TUNING.materials.matte_share_range))


def colour_held(materials: BasisMaterials, members: np.ndarray, rho_d: np.ndarray) -> tuple[BasisMaterials, np.ndarray]:
    """The lobe materials that hold texels with a lobe of their own (``rho_d (n, 3)``), and the
    clustered texels' ``members (m,)`` renumbered to them (-1: in none). Such a texel is labelled by
    its colour (``class_costs``' likeliest class); a material it falls to fewer than ``TUNING.materials.min_members``
    times holds none. Why: a cluster whose members' colours all fall to another material (the same
    colour, a larger share) is another reading of that material's traces — the box's line-brushed
    metal seen through one LED solves isotropic and sharp and clusters apart, and 31% of its lobeless
    texels took that lobe, their tangents lost (docs/history/accuracy.md)."""
    if len(materials) == 0:
        return materials, members
    label = np.argmin(class_costs(rho_d, materials), 1) - 1
    held = np.bincount(label[label >= 0], minlength=len(materials)) >= TUNING.materials.min_members
    index = np.where(held, np.cumsum(held) - 1, -1)
    return materials.subset(held), np.where(members >= 0, index[members.clip(0)], -1)


def candidates(prior: np.ndarray, materials: BasisMaterials) -> np.ndarray:
    """The lobe materials ``(N, K)`` worth judging by a texel's trace, from ``class_costs`` at its
    rho_d without a lobe: those within ``TUNING.materials.candidate_margin`` of its likeliest by colour, and the
    broad ones (smaller alpha >= ``TUNING.materials.broad_alpha``): under such a lobe the texel's rho_d may be far
    darker than without one (a sharp lobe the trace misses leaves it as it is)."""
    lobe = prior[:, 1:]
    near = lobe <= lobe.min(1, keepdims=True, initial=math.inf) + TUNING.materials.candidate_margin
    return near | (materials.alpha[:, 1] >= TUNING.materials.broad_alpha)[None]
