"""The geometry fit's per-texel work as one compiled loop (numba, parallel over texels).

``fit.geometry`` states the method: the K lights, the IRLS solves for A (6 unknowns) and the
Levenberg-Marquardt on the log(1 + x) residual in A-space. Done tensor by tensor, every step builds
a dozen ``(N, K)`` temporaries and every texel waits for the slowest; here each texel walks its K
lights once per step, keeps nothing but sums, and stops when its own steps stop paying.

Convention: the lumitexel frame (wo = +z); light tables as ``fit.geometry.light_table`` (float64);
``specular (N, L)`` lumitexels (NaN/inf read as 0, negative values as 0). Results per texel
(``out (N, 12)``): n (3), t (3), alpha_x, alpha_y (in [ALPHA_MIN, ALPHA_MAX]), rho_s, ok (1.0 where a
lobe was found) — not yet in canonical form — then finite (1.0 where every value is) and the peak.
Everything in float64; the 3x3 eigenproblem by cyclic Jacobi, the 6x6 systems by
Gaussian elimination with partial pivoting (no LAPACK call per texel).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ..io.jit import compiled
from ..physics.brdf import ALPHA_MAX, ALPHA_MIN, RHO_S_MAX

# the bounds the loop clamps to, passed as an argument: a module constant compiled into a cached loop
# would not change with brdf.py (numba keys its disk cache on the function's own file)
BOUNDS = np.array([ALPHA_MIN, ALPHA_MAX, RHO_S_MAX])

# numba's fast-math flags without nnan/ninf: the loop relies on finiteness tests
_FAST = {"nsz", "arcp", "contract", "afn", "reassoc"}
# LM damping: start, bounds. Start nearly Gauss-Newton: from 1e-3, lobes at the sharp bound crept for
# ~6 steps before the damping let them move (measured; tests/fit/test_lobe_loop.py)
_LAM0, _LAM_MIN, _LAM_MAX = 1e-6, 1e-9, 1e6
_REJECTS = 3  # consecutive rejected LM steps (damping x1000) after which a texel is done
# an accepted, nearly Gauss-Newton step (damping <= _LAM0) improving the cost by less than this fraction
# ends the LM: the texel has converged (after rejections, small steps gain little on the way too)
_MIN_GAIN = 1e-3
_MIN_NZ = 0.05  # a lobe whose normal tilts further from the lumitexel's z is not taken


@compiled(inline="always")
def _g1(vx, vy, vz, ax, ay):  # pragma: no cover - compiled
    """brdf.smith_g1 for one unit vector in the lobe's frame."""
    if vz <= 0.0:
        return 0.0
    return 2.0 * vz / (vz + math.sqrt(max((ax * vx) ** 2 + (ay * vy) ** 2 + vz * vz, 1e-20)))


@compiled(fastmath=_FAST)
def _phi(idx, wi, r2, fres, lobe, out):  # pragma: no cover - compiled
    """Phi = F G1(wi) G1(wo) / (4 cos_o r^2) toward the lights ``idx`` under ``lobe`` (n 0:3, t 3:6,
    ax 6, ay 7), into ``out``; 0 below the lobe's horizon."""
    nx, ny, nz = lobe[0], lobe[1], lobe[2]
    tx, ty, tz = lobe[3], lobe[4], lobe[5]
    ax, ay = lobe[6], lobe[7]
    bx, by, bz = ny * tz - nz * ty, nz * tx - nx * tz, nx * ty - ny * tx  # b = n x t
    g_o = _g1(tz, bz, nz, ax, ay)  # wo = +z in the lobe's frame: (t_z, b_z, n_z)
    c_o = 4.0 * max(nz, 1e-4)
    for j in range(idx.shape[0]):
        li = idx[j]
        w0, w1, w2 = wi[li, 0], wi[li, 1], wi[li, 2]
        iz = nx * w0 + ny * w1 + nz * w2
        if iz <= 0.0:
            out[j] = 0.0
            continue
        ix, iy = tx * w0 + ty * w1 + tz * w2, bx * w0 + by * w1 + bz * w2
        out[j] = fres[li] * _g1(ix, iy, iz, ax, ay) * g_o / (c_o * r2[li])


@compiled()
def _eigh3(A, evals, evecs):  # pragma: no cover - compiled
    """Eigenvalues (ascending) and unit eigenvectors (columns) of the symmetric 3x3 ``A`` (destroyed)
    by cyclic Jacobi rotations; False if ``A`` is not finite."""
    for i in range(3):
        for j in range(3):
            if not math.isfinite(A[i, j]):
                return False
            evecs[i, j] = 1.0 if i == j else 0.0
    for _ in range(60):
        off = A[0, 1] ** 2 + A[0, 2] ** 2 + A[1, 2] ** 2
        if off <= 1e-32 * (A[0, 0] ** 2 + A[1, 1] ** 2 + A[2, 2] ** 2) or off == 0.0:
            break
        for p, q in ((0, 1), (0, 2), (1, 2)):
            apq = A[p, q]
            if apq == 0.0:
                continue
            theta = (A[q, q] - A[p, p]) / (2.0 * apq)
            if abs(theta) > 1e150:
                t = 0.5 / theta
            else:
                t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + math.sqrt(theta * theta + 1.0))
            c = 1.0 / math.sqrt(t * t + 1.0)
            s = t * c
            for k in range(3):  # A <- A P, then P^T A; evecs <- evecs P
                akp, akq = A[k, p], A[k, q]
                A[k, p], A[k, q] = c * akp - s * akq, s * akp + c * akq
            for k in range(3):
                apk, aqk = A[p, k], A[q, k]
                A[p, k], A[q, k] = c * apk - s * aqk, s * apk + c * aqk
            for k in range(3):
                vkp, vkq = evecs[k, p], evecs[k, q]
                evecs[k, p], evecs[k, q] = c * vkp - s * vkq, s * vkp + c * vkq
    for i in range(3):
        evals[i] = A[i, i]
    for i in range(2):  # sort ascending, vectors along
        for j in range(2 - i):
            if evals[j] > evals[j + 1]:
                evals[j], evals[j + 1] = evals[j + 1], evals[j]
                for k in range(3):
                    evecs[k, j], evecs[k, j + 1] = evecs[k, j + 1], evecs[k, j]
    return True


@compiled()
def _solve6(H, b, x):  # pragma: no cover - compiled
    """x = H^-1 b for the 6x6 ``H`` (destroyed; ``b`` too) by Gaussian elimination with partial
    pivoting; False where a pivot vanishes or the result is not finite."""
    n = 6
    for c in range(n):
        p = c
        for r in range(c + 1, n):
            if abs(H[r, c]) > abs(H[p, c]):
                p = r
        if not H[p, c] != 0.0:  # zero or NaN
            return False
        if p != c:
            for k in range(n):
                H[c, k], H[p, k] = H[p, k], H[c, k]
            b[c], b[p] = b[p], b[c]
        for r in range(c + 1, n):
            f = H[r, c] / H[c, c]
            for k in range(c, n):
                H[r, k] -= f * H[c, k]
            b[r] -= f * b[c]
    for c in range(n - 1, -1, -1):
        s = b[c]
        for k in range(c + 1, n):
            s -= H[c, k] * x[k]
        x[c] = s / H[c, c]
        if not math.isfinite(x[c]):
            return False
    return True


@compiled()
def _lobe_from_a(a, lobe, A, evals, evecs, bounds):  # pragma: no cover - compiled
    """GGX reading of A's 6 entries (a00, a11, a22, a01, a02, a12) into ``lobe`` (n, t, ax, ay,
    rho_s; alphas clamped to ``bounds``' first two); False where A is not positive definite."""
    A[0, 0], A[1, 1], A[2, 2] = a[0], a[1], a[2]
    A[0, 1] = A[1, 0] = a[3]
    A[0, 2] = A[2, 0] = a[4]
    A[1, 2] = A[2, 1] = a[5]
    if not _eigh3(A, evals, evecs) or not evals[0] > 0.0:
        return False
    sign = -1.0 if evecs[2, 0] < 0.0 else 1.0  # the normal toward the lumitexel's +z
    for k in range(3):
        lobe[k] = sign * evecs[k, 0]
        lobe[3 + k] = evecs[k, 1]
    lam0 = evals[0]
    lobe[6] = min(max(math.sqrt(lam0 / max(evals[1], 1e-30)), bounds[0]), bounds[1])
    lobe[7] = min(max(math.sqrt(lam0 / max(evals[2], 1e-30)), bounds[0]), bounds[1])
    lobe[8] = math.pi * lobe[6] * lobe[7] / (lam0 * lam0)
    return True


@compiled()
def _a_from_lobe(lobe, a):  # pragma: no cover - compiled
    """A = sqrt(pi ax ay / rho_s) (n n^T + t t^T / ax^2 + b b^T / ay^2) as its 6 entries."""
    nx, ny, nz, tx, ty, tz = lobe[0], lobe[1], lobe[2], lobe[3], lobe[4], lobe[5]
    bx, by, bz = ny * tz - nz * ty, nz * tx - nx * tz, nx * ty - ny * tx
    ix, iy = 1.0 / lobe[6] ** 2, 1.0 / lobe[7] ** 2
    s = math.sqrt(math.pi * lobe[6] * lobe[7] / max(lobe[8], 1e-30))
    a[0] = s * (nx * nx + tx * tx * ix + bx * bx * iy)
    a[1] = s * (ny * ny + ty * ty * ix + by * by * iy)
    a[2] = s * (nz * nz + tz * tz * ix + bz * bz * iy)
    a[3] = s * (nx * ny + tx * ty * ix + bx * by * iy)
    a[4] = s * (nx * nz + tx * tz * ix + bx * bz * iy)
    a[5] = s * (ny * nz + ty * tz * ix + by * bz * iy)


@compiled()
def _kth_smallest(a, k):  # pragma: no cover - compiled
    """The ``k``-th smallest (0-based) of ``a`` (reordered in place): quickselect, Hoare's scheme
    with the median of three as pivot (np.partition took 6.6 s to compile, this 0.2 s)."""
    lo, hi = 0, a.shape[0] - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if a[mid] < a[lo]:
            a[mid], a[lo] = a[lo], a[mid]
        if a[hi] < a[lo]:
            a[hi], a[lo] = a[lo], a[hi]
        if a[hi] < a[mid]:
            a[hi], a[mid] = a[mid], a[hi]
        pivot = a[mid]
        i, j = lo, hi
        while i <= j:
            while a[i] < pivot:
                i += 1
            while pivot < a[j]:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            return a[k]
    return a[k]


_SAMPLE = 64  # values sampled to bracket the k-th smallest (``_select``)
_BRACKET = 8  # sample ranks on either side of the k-th's expected rank (~2 sigma at 64 samples)


@compiled()
def _kth_smallest_bracketed(values, k, scratch):  # pragma: no cover - compiled
    """The ``k``-th smallest (0-based) of ``values`` (not changed; no NaN): two bounds from a
    strided sample, one pass counting the values below the lower and gathering those between into
    ``scratch``, quickselect on those few (Floyd-Rivest's idea; a branch-free pass instead of a
    quickselect over all: 3x faster on 6144 lights). Falls back to a quickselect over all where the
    bounds miss the k-th."""
    L = values.shape[0]
    step = max(L // _SAMPLE, 1)
    ns = (L + step - 1) // step
    if ns >= 4 * _BRACKET:
        sample = scratch[L - ns : L]  # the top of scratch; the gather below fills it from the bottom
        for j in range(ns):
            sample[j] = values[j * step]
        centre = (k * ns) // L
        lo_rank, hi_rank = centre - _BRACKET, centre + _BRACKET
        lo = _kth_smallest(sample, lo_rank) if lo_rank >= 0 else -math.inf
        hi = _kth_smallest(sample, hi_rank) if hi_rank < ns else math.inf
        below, c = 0, 0
        for li in range(L):
            v = values[li]
            below += v < lo
            scratch[c] = v  # written always, kept when inside: no branch
            c += (v >= lo) & (v <= hi)
        if below <= k < below + c:
            return _kth_smallest(scratch[:c], k - below)
    scratch[:L] = values  # too few values to sample, or the bounds missed the k-th: all of them
    return _kth_smallest(scratch[:L], k)


@compiled()
def _select(values, k, idx, scratch):  # pragma: no cover - compiled
    """The ``k`` smallest of ``values`` (no NaN; ties at the k-th by index) into ``idx``, in index
    order; ``scratch`` is as long as ``values``."""
    thr = _kth_smallest_bracketed(values, k - 1, scratch)
    j = 0
    for li in range(values.shape[0]):  # at most k - 1 are below: idx[j] is in bounds, no branch
        idx[j] = li
        j += values[li] < thr
    for li in range(values.shape[0]):
        if j == k:
            break
        if values[li] == thr:
            idx[j] = li
            j += 1


@compiled(fastmath=_FAST)
def _residuals(idx, a, feats, phi, log_mk, r, g):  # pragma: no cover - compiled
    """log1p(Phi / (f.a)^2) - log1p(m) over the lights ``idx`` into ``r``, d r / d (f.a) into
    ``g``; the summed squares, inf where it is not finite."""
    cost = 0.0
    for j in range(idx.shape[0]):
        li = idx[j]
        y = feats[li, 0] * a[0] + feats[li, 1] * a[1] + feats[li, 2] * a[2]
        y += feats[li, 3] * a[3] + feats[li, 4] * a[4] + feats[li, 5] * a[5]
        if y > 0.0:
            mm = phi[j] / (y * y)
            g[j] = -2.0 * mm / ((1.0 + mm) * y)
        else:
            mm, g[j] = 0.0, 0.0
        r[j] = math.log1p(mm) - log_mk[j]
        cost += r[j] * r[j]
    return cost if math.isfinite(cost) else math.inf


@compiled(fastmath=_FAST)
def _normal_equations(idx, feats, w, y, H, b):  # pragma: no cover - compiled
    """H, b (filled) of min_a sum_j w_j (f_j . a - y_j)^2 over the lights ``idx`` (w_j = 0 skipped)."""
    H[:] = 0.0
    b[:] = 0.0
    for j in range(idx.shape[0]):
        if w[j] == 0.0:
            continue
        f = feats[idx[j]]
        for p in range(6):
            wf = w[j] * f[p]
            b[p] += wf * y[j]
            for q in range(p, 6):
                H[p, q] += wf * f[q]
    for p in range(6):
        for q in range(p):
            H[p, q] = H[q, p]


@compiled(fastmath=_FAST)
def _weighted_ls(idx, feats, y, w, a):  # pragma: no cover - compiled
    """a = argmin sum_j w_j (f_j . a - y_j)^2 (lightly regularised as the normal equations' scale
    asks); False where the system is singular."""
    H, b = np.zeros((6, 6)), np.zeros(6)
    _normal_equations(idx, feats, w, y, H, b)
    scale = 0.0
    for p in range(6):
        scale += H[p, p] / 6.0
    for p in range(6):
        H[p, p] += 1e-9 * max(scale, 1e-30)
    return _solve6(H, b, a)


@compiled(parallel=True)
def fit_lobes(specular, wi, r2, fres, feats, iterations, k, gn_steps, bounds, out):  # pragma: no cover
    """Per texel of ``specular (N, L)``: the K lights, ``iterations`` IRLS solves and up to
    ``gn_steps`` LM steps (not for a texel with a value that is not finite), alphas and rho_s
    clamped to ``bounds`` (``BOUNDS``); fills ``out (N, 12)`` (module docstring). The parallel
    loop only hands texels out (its body compiles slowly)."""
    for i in numba.prange(specular.shape[0]):
        _fit_texel(specular[i], wi, r2, fres, feats, iterations, k, gn_steps, bounds, out[i])


@compiled(fastmath=_FAST)
def _fit_texel(specular, wi, r2, fres, feats, iterations, k, gn_steps, bounds, out):  # pragma: no cover
    """``fit_lobes`` for one texel: ``specular (L,)`` in, ``out (12,)`` filled."""
    L = specular.shape[0]
    m = np.empty(L)  # the texel's lumitexel, NaN/inf as 0, clipped at 0
    finite = True
    peak = 0.0
    for li in range(L):
        v = specular[li]
        if not math.isfinite(v):
            finite, v = False, 0.0
        m[li] = max(v, 0.0)
        peak = max(peak, m[li])
    out[10], out[11] = (1.0 if finite else 0.0), peak
    lobe = np.array([0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.1, 0.1, 1.0])  # n, t, ax, ay, rho_s
    trial = np.zeros(9)
    a_cur, a_new = np.zeros(6), np.zeros(6)
    A, evals, evecs = np.zeros((3, 3)), np.zeros(3), np.zeros((3, 3))
    idx = np.empty(k, np.int64)
    mk, phi, y, w = np.empty(k), np.empty(k), np.empty(k), np.empty(k)
    # first pass: the K lights where m / Phi0 (n = z, G = 1) is largest
    values, scratch = np.empty(L), np.empty(L)
    for li in range(L):
        values[li] = -m[li] * 4.0 * r2[li] / fres[li]
    _select(values, k, idx, scratch)
    ok = False
    have_a = False
    for it in range(iterations):
        if it < 2:  # the lights change once, after the first solve
            for j in range(k):
                mk[j] = m[idx[j]]
        if have_a:
            _phi(idx, wi, r2, fres, lobe, phi)
        else:
            for j in range(k):
                phi[j] = fres[idx[j]] / (4.0 * r2[idx[j]])
        for j in range(k):
            f = feats[idx[j]]
            valid = mk[j] > 1e-6 * peak and phi[j] > 0.0
            y[j] = 1.0 / math.sqrt(mk[j] / max(phi[j], 1e-30)) if valid else 1.0
            # d log1p(m) = -2 m / (1 + m) dy / y: log1p-space LS ...
            w[j] = (2.0 * mk[j] / ((1.0 + mk[j]) * y[j])) ** 2 if valid else 0.0
            if have_a and valid:  # ... and away from the fit, the true log1p residual (IRLS)
                y_model = f[0] * a_cur[0] + f[1] * a_cur[1] + f[2] * a_cur[2]
                y_model += f[3] * a_cur[3] + f[4] * a_cur[4] + f[5] * a_cur[5]
                dy = y_model - y[j]
                if abs(dy) > 1e-3 * y[j] and y_model > 0.0:
                    m_model = min(phi[j] / max(y_model, 1e-12) ** 2, 1e30)
                    w[j] = ((math.log1p(m_model) - math.log1p(mk[j])) / dy) ** 2
        solved = _weighted_ls(idx, feats, y, w, a_new)
        take = solved and _lobe_from_a(a_new, trial, A, evals, evecs, bounds) and trial[2] > _MIN_NZ
        if take:
            lobe[:] = trial
        if take or (solved and not have_a):  # the first solve's A weighs the next, lobe or not
            a_cur[:] = a_new
        have_a = True
        ok = ok or take
        if it == 0 and iterations > 1 and ok:  # re-select: the K lights where the lobe is brightest
            for li in range(L):
                yl = feats[li, 0] * a_cur[0] + feats[li, 1] * a_cur[1] + feats[li, 2] * a_cur[2]
                yl += feats[li, 3] * a_cur[3] + feats[li, 4] * a_cur[4] + feats[li, 5] * a_cur[5]
                values[li] = yl if yl > 0.0 else math.inf
            _select(values, k, idx, scratch)
    lobe[8] = min(max(lobe[8], 1e-12), bounds[2] * 10)
    if ok and finite and gn_steps > 0:
        _levenberg_marquardt(m, idx, wi, r2, fres, feats, gn_steps, bounds, lobe, trial, mk, phi, y, w)
    for c in range(9):
        out[c] = lobe[c]
    out[9] = 1.0 if ok else 0.0


@compiled(fastmath=_FAST)
def _levenberg_marquardt(
    m_i, idx, wi, r2, fres, feats, steps, bounds, lobe, trial, log_mk, phi, r, g
):  # pragma: no cover - compiled
    """LM on the log1p residual over the lights ``idx`` in A-space (Jacobian g_l f_l with Phi frozen
    within a step); a step is kept only where the true residual (new Phi, clamped alphas) falls.
    Updates ``lobe``; the other arrays are scratch of length K."""
    k = idx.shape[0]
    for j in range(k):
        log_mk[j] = math.log1p(m_i[idx[j]])
    a, a2, step = np.zeros(6), np.zeros(6), np.zeros(6)
    r_new, g_new, g2, target = np.empty(k), np.empty(k), np.empty(k), np.empty(k)
    H, b = np.zeros((6, 6)), np.zeros(6)
    JtJ = np.zeros((6, 6))
    A, evals, evecs = np.zeros((3, 3)), np.zeros(3), np.zeros((3, 3))
    _a_from_lobe(lobe, a)
    _phi(idx, wi, r2, fres, lobe, phi)
    cost = _residuals(idx, a, feats, phi, log_mk, r, g)
    lam = _LAM0
    rejects = 0
    for _ in range(steps):
        # the Gauss-Newton step: min sum_j (g_j f_j . step + r_j)^2 = sum_j g_j^2 (f_j . step + r_j / g_j)^2
        for j in range(k):
            g2[j] = g[j] * g[j]
            target[j] = -r[j] / g[j] if g[j] != 0.0 else 0.0
        _normal_equations(idx, feats, g2, target, JtJ, b)
        H[:] = JtJ
        for p in range(6):
            H[p, p] += lam * (JtJ[p, p] + 1e-12)
        better = False
        if _solve6(H, b, step):
            for p in range(6):
                a2[p] = a[p] + step[p]
            if _lobe_from_a(a2, trial, A, evals, evecs, bounds) and trial[2] > _MIN_NZ:
                _a_from_lobe(trial, a2)
                _phi(idx, wi, r2, fres, trial, phi)
                cost_new = _residuals(idx, a2, feats, phi, log_mk, r_new, g_new)
                better = cost_new < cost
        if better:
            gain = cost - cost_new
            lobe[:] = trial
            a[:] = a2
            r[:] = r_new
            g[:] = g_new
            cost = cost_new
            if gain <= _MIN_GAIN * (cost + gain) and lam <= _LAM0:
                break
            lam = max(lam * 0.2, _LAM_MIN)
            rejects = 0
        else:
            lam = min(lam * 10.0, _LAM_MAX)
            rejects += 1
            if rejects >= _REJECTS:
                break
