import numpy as np
import pytest
import torch
from lobes import exact_lobes

from ntp_engine.fit.geometry import fit_geometry, light_table
from ntp_engine.fit.lobe_loop import BOUNDS, _eigh3, _kth_smallest, _select, _solve6, fit_lobes
from ntp_engine.physics.lumitexel import SPECULAR_RES, specular_lumitexel


@pytest.mark.parametrize("spectrum", [(1.0, 2.0, 3.0), (1.0, 1.0, 5.0), (2.0, 2.0, 2.0), (1e-4, 1.0, 2.5e4)])
def test_eigh3_matches_lapack_with_repeated_and_spread_eigenvalues(spectrum):
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    A = q @ np.diag(spectrum) @ q.T
    evals, evecs = np.zeros(3), np.zeros((3, 3))
    assert _eigh3(A.copy(), evals, evecs)
    np.testing.assert_allclose(evals, np.linalg.eigvalsh(A), rtol=1e-10, atol=1e-12 * max(spectrum))
    np.testing.assert_allclose(evecs.T @ evecs, np.eye(3), atol=1e-12)  # orthonormal even where repeated
    np.testing.assert_allclose(A @ evecs, evecs * evals, atol=1e-9 * max(spectrum))


def test_eigh3_refuses_a_matrix_that_is_not_finite():
    A = np.eye(3)
    A[1, 2] = A[2, 1] = np.nan
    assert not _eigh3(A, np.zeros(3), np.zeros((3, 3)))


def test_solve6_matches_lapack_and_refuses_a_singular_system():
    rng = np.random.default_rng(1)
    H, b = rng.normal(size=(6, 6)), rng.normal(size=6)
    x = np.zeros(6)
    assert _solve6(H.copy(), b.copy(), x)
    np.testing.assert_allclose(x, np.linalg.solve(H, b), rtol=1e-10)
    H[:, 3] = 0.0
    assert not _solve6(H, b, x)


def test_select_takes_the_k_smallest_ties_by_index():
    values = np.array([5.0, 1.0, 3.0, 1.0, np.inf, 3.0, 0.5])
    idx = np.zeros(4, np.int64)
    _select(values, 4, idx, np.zeros(7))
    assert idx.tolist() == [1, 3, 6, 2]  # below the 4th smallest (3.0) in order, then the first 3.0


@pytest.mark.parametrize("layout", ["spread", "ties", "sample_misleads"])
def test_select_over_a_whole_lumitexel_is_a_stable_sort(layout):
    """The sampled bracket (``_kth_smallest_bracketed``) and its fallback where the sample misleads."""
    rng = np.random.default_rng(5)
    L, k = 6144, 384
    values = {
        "spread": rng.normal(size=L),
        "ties": rng.integers(0, 20, L).astype(float),
        "sample_misleads": rng.random(L),
    }[layout]
    values[rng.random(L) < 0.2] = np.inf
    if layout == "sample_misleads":
        values[:: L // 64] = -1.0  # every sampled value the smallest: the bracket misses the k-th
    idx = np.zeros(k, np.int64)
    _select(values, k, idx, np.zeros(L))
    assert sorted(idx.tolist()) == sorted(np.argsort(values, kind="stable")[:k].tolist())


@pytest.mark.parametrize("n", [1, 2, 7, 6144])
def test_quickselect_finds_every_order_statistic_with_many_ties(n):
    rng = np.random.default_rng(n)
    a = rng.integers(0, max(n // 4, 2), n).astype(float)  # many repeated values
    a[rng.random(n) < 0.1] = np.inf
    for k in {0, n // 3, n // 2, n - 1}:
        assert _kth_smallest(a.copy(), k) == np.sort(a)[k]


def test_each_texel_is_fitted_on_its_own():
    """A texel's fit does not depend on the other texels of its batch (each stops on its own)."""
    m, *_ = exact_lobes(24, seed=3)
    noisy = torch.expm1(torch.log1p(m) + 0.05 * torch.randn(m.shape, generator=torch.Generator().manual_seed(0)))
    together = fit_geometry(noisy.clamp_min(0))
    for i in (0, 7, 23):
        alone = fit_geometry(noisy[i : i + 1].clamp_min(0))
        assert torch.equal(alone.normal[0], together.normal[i]) and torch.equal(alone.alpha_y[0], together.alpha_y[i])
    threads = torch.get_num_threads()
    try:  # nor on how many threads share the texels
        torch.set_num_threads(1)
        one = fit_geometry(noisy.clamp_min(0))
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(one.normal, together.normal) and torch.equal(one.tangent, together.tangent)
    assert torch.equal(one.alpha_x, together.alpha_x) and torch.equal(one.rho_s, together.rho_s)


def test_sharp_lobes_converge_to_the_exact_lumitexel():
    """Lobes at the sharp bound need many damped steps before Gauss-Newton takes over: none may stop early."""
    m, n, t, ax, ay, rho = exact_lobes(256, seed=4)
    ay = torch.full_like(ay, 0.0062)
    m = specular_lumitexel(n, t, rho[:, None], ax, ay)[..., 0]
    f = fit_geometry(m, with_error=True)
    assert float(f.log_rmse.max()) < 1e-4


def test_the_loop_clamps_to_the_bounds_it_is_given():
    """The bounds are an argument, not constants compiled into the cached loop (numba would not
    recompile it when brdf.py changes)."""
    m, *_ = exact_lobes(32, seed=5)
    tab = {k: v.numpy() for k, v in light_table(SPECULAR_RES, "cpu", torch.float64).items()}
    outs = []
    for bounds in (BOUNDS, np.array([0.05, 0.08, 0.5])):
        out = np.zeros((len(m), 12))
        fit_lobes(m.float().numpy(), tab["wi"], tab["r2"], tab["fresnel"], tab["feats"], 3, 384, 10, bounds, out)
        outs.append(out)
    wide, narrow = outs
    assert (wide[:, 6:8] < 0.05).any() and (wide[:, 6:8] > 0.08).any()  # the default range is used
    assert narrow[:, 6:8].min() >= 0.05 and narrow[:, 6:8].max() <= 0.08 and narrow[:, 8].max() <= 5.0
