"""The refinement's pixel bases (``refine.policy``): Eq. 1 per entry summed over its emitters for unit
albedos — diffuse and specular, the specular one with its derivatives — each as one compiled loop
(numba, parallel over texels): no (texels x entries x emitters) temporaries, which made the torch
form ~70% of the refinement's time.

Convention: every vector in the texel's geometric frame; per texel n, entry v, emitter sample m:
unit ``wi (N, V, 3, M)`` toward the emitter — components first, each a contiguous vector over the
emitters (the loops' bodies have no branch, so they vectorise) — and ``drive`` per camera channel
(exposure included; 0 for padding). Diffuse: ``falloff (N, V, M)`` = w_q Psi / r^2; the basis is
linear in the shading normal, ``diffuse (N, V, 3 channels, 3)`` = sum_m [wi.n0 > 0] falloff drive_c
wi / pi, so a pixel is rho_d,c (basis_c . n) for any normal n near the ``n0`` that chose the
emitters above the horizon.
Specular: ``frame (N, 3, 3)`` rows t, b, n of the shading frame; the emitters packed
``(N, V, 6, M)`` (``pack_emitters``): rows wi_x, wi_y, wi_z, falloff times the drive per channel; unit
``wo (N, V, 3)``, ``alpha (N, 2)`` = (alpha_x, alpha_y) along (t, b); ``widening (N, V, 2)``,
optional: what each entry's pixel sample adds to alpha_x^2, alpha_y^2 on a curved surface
(``refine.footprint``), the lobe it sees then having sqrt(alpha^2 + widening), derivatives still by
the surface's log alphas. The lobe toward emitter m is F D G / (4 cos_i cos_o) cos_i falloff in the
cancelled Smith form of ``physics.brdf.ggx_specular``:
    lobe = cos_i+ F falloff / (pi ax ay q^2 (cos_i+ + L_i) (cos_o+ + L_o)),  0 where cos_o <= 0,
q = (h_x/ax)^2 + (h_y/ay)^2 + h_z^2 for the unit half vector h, L = |(ax v_x, ay v_y, v_z)| in
the shading frame, and F Schlick's with F0 0.04 on wi.h = |wi + wo| / 2 (computed in the loops,
like h: storing them per sample cost more than computing them).
Derivatives are by (omega_x, omega_y, omega_z, log alpha_x, log alpha_y), omega a rotation of the
shading frame at 0 (a shading-frame vector v turns by v x omega, so d/d omega = g x v for
g = d log(lobe) / d v, summed over wi, h and wo; F depends on wi.h only, which a rotation keeps).
``rows (N,)``, where given: texel n's inputs (frame, alpha, normal) belong to row ``rows[n]`` of
the per-entry arrays (a subset of texels without copying them); outputs have N rows.
Results, arithmetic and sums in the dtype of ``wi`` (float32 or float64: the scipy baseline
differentiates them numerically; the specular loop's float32 sums over an entry's ~100 emitters
differ from float64 ones by ~1e-7 relative, and the demo's refinement is ~10% faster).
"""

from __future__ import annotations

import functools
import math

import numba
import numpy as np
import torch
from torch import Tensor

from ..io.jit import compiled
from ..io.thread_pools import numba_threads_as_torch
from ..physics.brdf import F0_DIELECTRIC
from ..physics.pattern_sums import emitter_arrays
from ..scanner.scanner import Scanner

N_DERIVATIVES = 5  # omega (3), log alpha_x, log alpha_y
PACKED_ROWS = 6  # a packed emitter: wi (3), falloff times drive (3)


def loop_array(t: Tensor, dtype: torch.dtype) -> np.ndarray:
    """``t`` as a compiled loop reads it: a C-contiguous numpy array of ``dtype``."""
    return np.ascontiguousarray(t.detach().to(dtype).numpy())


def emitter_directions(
    scanner: Scanner, x: Tensor, frame: Tensor, live: Tensor, padding: bool
) -> tuple[Tensor, Tensor, Tensor]:
    """The per-sample inputs of the bases for entries at ``x (M, 3)`` (camera space) with geometric
    frames ``frame (M, 3, 3)`` (rows t^, b^, n^) and ``live (M,)`` (False: padding, no light), toward
    ``scanner``'s K emitter samples: ``wo (M, 3)``, ``wi (M, 3, K')`` and ``falloff`` = w_q Psi / r^2
    ``(M, K')``, all in the frame (``measurement.local_emitter_geometry``'s). With ``padding``,
    K' = K + 1: sample K points where sample 0 does and emits nothing. Computed in float64, returned
    in ``x``'s dtype; one compiled pass instead of a dozen (M, K) temporaries."""
    e = emitter_arrays(scanner)
    M, K = len(x), e.points.shape[1]
    out_k = K + 1 if padding else K
    dt = torch.empty(0, dtype=x.dtype).numpy().dtype
    # every element is written: no zeroing (a third of this pass's time)
    wo, wi = np.empty((M, 3), dt), np.empty((M, 3, out_k), dt)
    falloff, cos_l = np.empty((M, out_k), dt), np.empty((M, out_k), dt)
    with numba_threads_as_torch():
        _directions_loop(
            loop_array(x, torch.float64),
            loop_array(frame, torch.float64),
            np.ascontiguousarray(live.numpy().astype(np.bool_)),
            e.points,
            e.weights,
            e.normals,
            wo,
            wi,
            falloff,
            cos_l,
        )
    # Psi from its one torch home (the compiled loop leaves it out: numba's disk cache would not see
    # a change to a compiled helper in another module); the padding sample has cos 0: Psi 0
    f = torch.from_numpy(falloff).mul_(scanner.psi(torch.from_numpy(cos_l)))
    return torch.from_numpy(wo), torch.from_numpy(wi), f


def diffuse_basis(normal: Tensor, wi: Tensor, falloff: Tensor, drive: Tensor) -> Tensor:
    """The diffuse basis ``(N, V, 3, 3)`` (module docstring) for the normals ``normal (N, 3)`` that
    decide which emitters are above the horizon, ``wi (N, V, 3, K)``, ``falloff (N, V, K)`` and one
    drive for every entry ``(K, 3)``."""
    return diffuse_basis_and_margin(normal, wi, falloff, drive)[0]


def diffuse_basis_and_margin(
    normal: Tensor, wi: Tensor, falloff: Tensor, drive: Tensor, rows: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """``diffuse_basis`` and each entry's horizon margin ``(N, V)``: the smallest |wi . n| over its
    lit emitters (inf where none). A normal that moves by less than the margin (``|n' - n|``)
    leaves every emitter on its side of the horizon, so the basis the same (``diffuse_basis_near``)."""
    N, V = len(normal), falloff.shape[1]
    todo = np.ones((N, V), np.bool_)
    out = np.zeros((N, V, 3, 3), torch.empty(0, dtype=wi.dtype).numpy().dtype)
    margin = np.full((N, V), np.inf, out.dtype)
    _diffuse(normal, wi, falloff, drive, todo, out, margin, rows)
    return torch.from_numpy(out), torch.from_numpy(margin)


def diffuse_basis_near(
    normal: Tensor,
    wi: Tensor,
    falloff: Tensor,
    drive: Tensor,
    known: Tensor,
    known_normal: Tensor,
    margin: Tensor,
    rows: Tensor | None = None,
) -> Tensor:
    """``diffuse_basis`` for ``normal (N, 3)`` from ``known (N, V, 3, 3)``, the basis at
    ``known_normal (N, 3)`` with its ``margin (N, V)`` (``diffuse_basis_and_margin``): only the
    entries an emitter may cross the horizon of are summed again (a refined normal moves by a few
    degrees; most entries' emitters are far from their horizon). Equal to ``diffuse_basis``."""
    moved = torch.linalg.vector_norm(normal.to(margin.dtype) - known_normal.to(margin.dtype), dim=-1)
    # rounding of the dot products (|wi| = 1 to float precision) must not hide a crossing
    todo = margin <= moved[:, None] * (1 + 1e-3) + 1e-6
    out = known.clone()
    if bool(todo.any()):
        _diffuse(normal, wi, falloff, drive, todo.numpy(), out.numpy(), np.empty_like(margin.numpy()), rows)
    return out


def _rows(n: int, rows: Tensor | None) -> np.ndarray:
    """The per-entry arrays' row of each of ``n`` texels (all of them in order by default)."""
    return np.arange(n, dtype=np.int64) if rows is None else np.ascontiguousarray(rows.numpy().astype(np.int64))


def _diffuse(
    normal: Tensor,
    wi: Tensor,
    falloff: Tensor,
    drive: Tensor,
    todo: np.ndarray,
    out: np.ndarray,
    margin: np.ndarray,
    rows: Tensor | None,
) -> None:
    """The compiled loop's call: fills ``out`` and ``margin`` where ``todo (N, V)``."""
    d = wi.dtype
    with numba_threads_as_torch():
        arrays = [loop_array(x, d) for x in (normal, wi, falloff, drive.T)]
        _diffuse_loop(_rows(len(normal), rows), *arrays, np.ascontiguousarray(todo), _constants(out.dtype), out, margin)


def pack_emitters(wi: Tensor, falloff: Tensor, drive: Tensor) -> Tensor:
    """Emitters as the specular loop reads them, ``(N, V, 6, M)`` (module docstring): rows wi x, y,
    z and falloff times the drive per channel, each a vector over the M emitters, from ``wi (N, V,
    3, M)``, ``falloff (N, V, M)`` and ``drive (N, V, M, 3)`` or one for every entry ``(M, 3)``."""
    N, V, M = falloff.shape
    out = torch.empty(N, V, PACKED_ROWS, M, dtype=wi.dtype)
    out[:, :, :3] = wi
    out[:, :, 3:] = falloff[:, :, None] * drive.to(wi.dtype).transpose(-1, -2)
    return out


def specular_basis(
    frame: Tensor,
    emitters: Tensor,
    wo: Tensor,
    alpha: Tensor,
    rows: Tensor | None = None,
    widening: Tensor | None = None,
) -> Tensor:
    """The unit-rho_s pixel basis ``(N, V, 3)`` = sum_m lobe_m drive_m (module docstring) of the
    packed ``emitters`` (``pack_emitters``)."""
    return _specular(frame, emitters, wo, alpha, rows, widening, False)[0]


def specular_basis_and_derivatives(
    frame: Tensor,
    emitters: Tensor,
    wo: Tensor,
    alpha: Tensor,
    rows: Tensor | None = None,
    widening: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """``specular_basis`` and its derivatives ``(N, V, 5, 3)`` by (omega, log alpha_x, log alpha_y)
    (module docstring), in one pass."""
    return _specular(frame, emitters, wo, alpha, rows, widening, True)


def _specular(
    frame: Tensor,
    emitters: Tensor,
    wo: Tensor,
    alpha: Tensor,
    rows: Tensor | None,
    widening: Tensor | None,
    derivatives: bool,
) -> tuple[Tensor, Tensor]:
    """The compiled loop's call; the derivatives ``(0, 0, 5, 3)`` unless asked for."""
    N, V = len(frame), emitters.shape[1]
    dt = emitters.dtype
    arrays = [loop_array(x, dt) for x in (frame, emitters, wo, alpha)]
    # per entry in the loop: small torch ops between compiled loops cost ~1 ms each (thread wake-ups)
    wide = np.zeros((0, 0, 2), arrays[1].dtype) if widening is None else loop_array(widening, dt)
    spec = np.zeros((N, V, 3), arrays[1].dtype)
    ds = np.zeros((N, V, N_DERIVATIVES, 3) if derivatives else (0, 0, N_DERIVATIVES, 3), spec.dtype)
    with numba_threads_as_torch():
        _specular_loop(_rows(N, rows), *arrays, wide, _constants(spec.dtype), derivatives, spec, ds)
    return torch.from_numpy(spec), torch.from_numpy(ds)


@functools.cache
def _constants(dtype: np.dtype) -> np.ndarray:
    """The compiled loops' numbers in their working ``dtype``: 0, 1, 1/2, 4, pi, Schlick's F0 and the
    guards 1e-30, 1e-20, 1e-12, and inf (a float64 literal would make float32 arithmetic float64: the
    specular loop 1.54x slower without derivatives, 1.44x with, measured)."""
    return np.array([0.0, 1.0, 0.5, 4.0, math.pi, F0_DIELECTRIC, 1e-30, 1e-20, 1e-12, math.inf], dtype)


def lobe_weights(
    frame: Tensor,
    wi: Tensor,
    wo: Tensor,
    falloff: Tensor,
    alpha: Tensor,
    rows: Tensor | None = None,
) -> Tensor:
    """Each emitter's lobe for unit drive ``(N, V, M)`` (module docstring; ``refine.policy`` ranks the
    emitter blocks by it) of ``wi (N', V, 3, M)`` and ``falloff (N', V, M)``, in one compiled pass
    instead of a dozen (N, V, M) torch temporaries."""
    arrays = [loop_array(x, wi.dtype) for x in (frame, wi, wo, falloff, alpha)]
    N = len(frame)
    out = np.zeros((N, *falloff.shape[1:]), arrays[1].dtype)
    with numba_threads_as_torch():
        _lobe_loop(_rows(N, rows), *arrays, _constants(out.dtype), out)
    return torch.from_numpy(out)


def selected_emitters(
    top: Tensor,
    members: Tensor,
    fine: tuple[Tensor, Tensor, Tensor],
    coarse: tuple[Tensor, Tensor, Tensor],
    rows: Tensor | None = None,
) -> Tensor:
    """The specular basis' packed emitters (``pack_emitters``) when blocks of samples are summed
    sample by sample only where the lobe is: per entry, the samples of its E blocks ``top (N, V,
    E)`` (``members (C, S)``: a block's sample indices), then the other blocks' coarse emitters in
    block order. ``fine`` = (wi ``(N', V, 3, K)``, falloff ``(N', V, K)``, drive ``(K, 3)``) per
    sample, ``coarse`` the same per block (C). Returns ``(N, V, 6, M)`` with M = E S + C - E
    emitters per entry; one compiled pass."""
    N, V, E = top.shape
    C, S = members.shape
    dt = fine[0].dtype
    out = torch.empty(N, V, PACKED_ROWS, E * S + C - E, dtype=dt)
    with numba_threads_as_torch():
        _select_loop(
            _rows(N, rows),
            loop_array(top, torch.int64),
            loop_array(members, torch.int64),
            *(loop_array(x, dt) for x in fine),
            *(loop_array(x, dt) for x in coarse),
            out.numpy(),
        )
    return out


@compiled(parallel=True, fastmath=True)
def _diffuse_loop(rows, normal, wi, falloff, drive, todo, consts, out, margin):  # pragma: no cover
    """Fills ``out (N, V, 3, 3)`` and ``margin (N, V)`` where ``todo (N, V)`` (see
    ``diffuse_basis_and_margin``), texel n from row ``rows[n]`` of ``wi`` and ``falloff``; ``drive
    (3, K)`` one row per channel; ``consts``: ``_constants``' (the arithmetic in the arrays' dtype)."""
    zero, one, pi, inf = consts[0], consts[1], consts[4], consts[9]
    N, V, K = out.shape[0], falloff.shape[1], falloff.shape[2]
    dr0, dr1, dr2 = drive[0], drive[1], drive[2]
    for n in numba.prange(N):
        r = rows[n]
        n0, n1, n2 = normal[n, 0], normal[n, 1], normal[n, 2]
        for v in range(V):
            if not todo[n, v]:
                continue
            a00 = a01 = a02 = a10 = a11 = a12 = a20 = a21 = a22 = zero
            low = inf
            wx, wy, wz, fv = wi[r, v, 0], wi[r, v, 1], wi[r, v, 2], falloff[r, v]
            # no branch in the body (an emitter below the horizon is multiplied by 0): it vectorises
            for k in range(K):
                f = fv[k]
                x, y, z = wx[k], wy[k], wz[k]
                c = n0 * x + n1 * y + n2 * z
                low = min(low, abs(c) if f != zero else inf)
                f = f if c > zero else zero
                d0, d1, d2 = f * dr0[k], f * dr1[k], f * dr2[k]
                a00 += d0 * x
                a01 += d0 * y
                a02 += d0 * z
                a10 += d1 * x
                a11 += d1 * y
                a12 += d1 * z
                a20 += d2 * x
                a21 += d2 * y
                a22 += d2 * z
            c = one / pi
            out[n, v, 0, 0], out[n, v, 0, 1], out[n, v, 0, 2] = a00 * c, a01 * c, a02 * c
            out[n, v, 1, 0], out[n, v, 1, 1], out[n, v, 1, 2] = a10 * c, a11 * c, a12 * c
            out[n, v, 2, 0], out[n, v, 2, 1], out[n, v, 2, 2] = a20 * c, a21 * c, a22 * c
            margin[n, v] = low


@compiled(parallel=True, fastmath=True)
def _specular_loop(rows, frame, emitters, wo, alpha, widening, consts, derivatives, spec, ds):  # pragma: no cover
    """Fills ``spec (N, V, 3)`` and, with ``derivatives``, ``ds (N, V, 5, 3)`` (see the module);
    ``consts``: ``_constants``' (the arithmetic in the arrays' dtype)."""
    zero, one, half, four, pi = consts[0], consts[1], consts[2], consts[3], consts[4]
    f0, tiny, small, eps = consts[5], consts[6], consts[7], consts[8]
    N, V, M = spec.shape[0], emitters.shape[1], emitters.shape[3]
    for n in numba.prange(N):
        r = rows[n]
        t0, t1, t2 = frame[n, 0, 0], frame[n, 0, 1], frame[n, 0, 2]
        b0, b1, b2 = frame[n, 1, 0], frame[n, 1, 1], frame[n, 1, 2]
        n0, n1, n2 = frame[n, 2, 0], frame[n, 2, 1], frame[n, 2, 2]
        a0x, a0y = alpha[n, 0], alpha[n, 1]
        widened = widening.shape[0] > 0
        for v in range(V):
            ax2, ay2 = a0x * a0x, a0y * a0y
            if widened:  # the lobe this entry's pixel sample sees
                ax2 += widening[n, v, 0]
                ay2 += widening[n, v, 1]
            ax, ay = math.sqrt(ax2), math.sqrt(ay2)
            iax2, iay2 = one / ax2, one / ay2
            # d log(seen alpha) / d log alpha
            cx, cy = a0x * a0x * iax2, a0y * a0y * iay2
            ox = t0 * wo[r, v, 0] + t1 * wo[r, v, 1] + t2 * wo[r, v, 2]
            oy = b0 * wo[r, v, 0] + b1 * wo[r, v, 1] + b2 * wo[r, v, 2]
            oz = n0 * wo[r, v, 0] + n1 * wo[r, v, 1] + n2 * wo[r, v, 2]
            if oz <= zero:
                continue  # the view-side Smith factor: no lobe seen from below
            so0, so1 = ax2 * ox * ox, ay2 * oy * oy
            lam_o = math.sqrt(max(so0 + so1 + oz * oz, small))
            a_o = oz + lam_o
            seen = one / (pi * ax * ay * a_o)
            e = emitters[r, v]
            s0 = s1 = s2 = zero
            # per-emitter sums of lobe * d log(lobe) * drive (5 derivatives x 3 channels)
            g00 = g01 = g02 = g10 = g11 = g12 = g20 = g21 = g22 = zero
            g30 = g31 = g32 = g40 = g41 = g42 = zero
            # no branch in the body (an emitter below the horizon is multiplied by 0): it vectorises
            for m in range(M):
                wx, wy, wz = e[0, m], e[1, m], e[2, m]
                ix = t0 * wx + t1 * wy + t2 * wz
                iy = b0 * wx + b1 * wy + b2 * wz
                iz = n0 * wx + n1 * wy + n2 * wz
                # the half vector, unnormalised: q = (h^_x / ax)^2 + (h^_y / ay)^2 + h^_z^2 = hq / h2
                hx, hy, hz = ix + ox, iy + oy, iz + oz
                h2 = hx * hx + hy * hy + hz * hz
                hq = max(hx * hx * iax2 + hy * hy * iay2 + hz * hz, tiny)
                # Schlick's F on wi.h^ = |wi + wo| / 2 (unit wi, wo)
                u = one - min(half * math.sqrt(h2), one)
                fresnel = f0 + (one - f0) * (u * u) * (u * u) * u
                izp = max(iz, zero)
                si0, si1 = ax2 * ix * ix, ay2 * iy * iy
                lam_i = math.sqrt(max(si0 + si1 + iz * iz, small))
                a_i = izp + lam_i
                d = h2 / hq
                lobe = izp * fresnel * d * d / a_i  # per unit falloff x drive
                d0, d1, d2 = lobe * e[3, m], lobe * e[4, m], lobe * e[5, m]
                s0 += d0
                s1 += d1
                s2 += d2
                if derivatives:
                    # g = d log(lobe) / d v for v = h (D), wi (cos_i / (cos_i + L_i)); d/d omega = g x v
                    # (h's length cancels: the unnormalised h serves)
                    c = -four / hq
                    ghx, ghy, ghz = c * hx * iax2, c * hy * iay2, c * hz
                    k = -one / (a_i * lam_i)
                    gix, giy, giz = k * ax2 * ix, k * ay2 * iy, k * iz + one / max(iz, eps) - one / a_i
                    w0 = (giy * iz - giz * iy) + (ghy * hz - ghz * hy)
                    w1 = (giz * ix - gix * iz) + (ghz * hx - ghx * hz)
                    w2 = (gix * iy - giy * ix) + (ghx * hy - ghy * hx)
                    la_x = -one + four * hx * hx * iax2 / hq + k * si0
                    la_y = -one + four * hy * hy * iay2 / hq + k * si1
                    g00 += w0 * d0
                    g01 += w0 * d1
                    g02 += w0 * d2
                    g10 += w1 * d0
                    g11 += w1 * d1
                    g12 += w1 * d2
                    g20 += w2 * d0
                    g21 += w2 * d1
                    g22 += w2 * d2
                    g30 += la_x * d0
                    g31 += la_x * d1
                    g32 += la_x * d2
                    g40 += la_y * d0
                    g41 += la_y * d1
                    g42 += la_y * d2
            spec[n, v, 0], spec[n, v, 1], spec[n, v, 2] = s0 * seen, s1 * seen, s2 * seen
            if not derivatives:
                continue
            # the view side (same for every emitter): g_o = d log(1 / (cos_o + L_o)) / d wo
            k = -one / (a_o * lam_o)
            gox, goy, goz = k * ax2 * ox, k * ay2 * oy, k * oz - one / a_o
            w0 = goy * oz - goz * oy
            w1 = goz * ox - gox * oz
            w2 = gox * oy - goy * ox
            la_x, la_y = k * so0, k * so1
            ds[n, v, 0, 0], ds[n, v, 0, 1], ds[n, v, 0, 2] = g00 + w0 * s0, g01 + w0 * s1, g02 + w0 * s2
            ds[n, v, 1, 0], ds[n, v, 1, 1], ds[n, v, 1, 2] = g10 + w1 * s0, g11 + w1 * s1, g12 + w1 * s2
            ds[n, v, 2, 0], ds[n, v, 2, 1], ds[n, v, 2, 2] = g20 + w2 * s0, g21 + w2 * s1, g22 + w2 * s2
            ds[n, v, 3, 0], ds[n, v, 3, 1], ds[n, v, 3, 2] = g30 + la_x * s0, g31 + la_x * s1, g32 + la_x * s2
            ds[n, v, 4, 0], ds[n, v, 4, 1], ds[n, v, 4, 2] = g40 + la_y * s0, g41 + la_y * s1, g42 + la_y * s2
            for i in range(3):  # the emitters' sums left out the view side's 1 / (cos_o + L_o)
                for c in range(3):
                    ds[n, v, i, c] *= seen
                ds[n, v, 3, i] *= cx * seen
                ds[n, v, 4, i] *= cy * seen


@compiled(parallel=True, fastmath=True)
def _lobe_loop(rows, frame, wi, wo, ff, alpha, consts, out):  # pragma: no cover - compiled
    """Fills ``out (N, V, M)`` (see ``lobe_weights``), texel n from row ``rows[n]`` of the per-entry
    arrays; ``consts``: ``_constants``' (the arithmetic in the arrays' dtype)."""
    zero, one, half, pi = consts[0], consts[1], consts[2], consts[4]
    f0, tiny, small = consts[5], consts[6], consts[7]
    N, V, M = out.shape
    for n in numba.prange(N):
        r = rows[n]
        ax, ay = alpha[n, 0], alpha[n, 1]
        ax2, ay2 = ax * ax, ay * ay
        iax2, iay2 = one / ax2, one / ay2
        t0, t1, t2 = frame[n, 0, 0], frame[n, 0, 1], frame[n, 0, 2]
        b0, b1, b2 = frame[n, 1, 0], frame[n, 1, 1], frame[n, 1, 2]
        n0, n1, n2 = frame[n, 2, 0], frame[n, 2, 1], frame[n, 2, 2]
        for v in range(V):
            oz = n0 * wo[r, v, 0] + n1 * wo[r, v, 1] + n2 * wo[r, v, 2]
            if oz <= zero:
                continue
            ox = t0 * wo[r, v, 0] + t1 * wo[r, v, 1] + t2 * wo[r, v, 2]
            oy = b0 * wo[r, v, 0] + b1 * wo[r, v, 1] + b2 * wo[r, v, 2]
            seen = one / (pi * ax * ay * (oz + math.sqrt(max(ax2 * ox * ox + ay2 * oy * oy + oz * oz, small))))
            for m in range(M):
                wx, wy, wz = wi[r, v, 0, m], wi[r, v, 1, m], wi[r, v, 2, m]
                ix = t0 * wx + t1 * wy + t2 * wz
                iy = b0 * wx + b1 * wy + b2 * wz
                iz = n0 * wx + n1 * wy + n2 * wz
                hx, hy, hz = ix + ox, iy + oy, iz + oz
                h2 = hx * hx + hy * hy + hz * hz
                d = h2 / max(hx * hx * iax2 + hy * hy * iay2 + hz * hz, tiny)
                u = one - min(half * math.sqrt(h2), one)
                fresnel = f0 + (one - f0) * (u * u) * (u * u) * u
                izp = max(iz, zero)
                lam_i = math.sqrt(max(ax2 * ix * ix + ay2 * iy * iy + iz * iz, small))
                out[n, v, m] = izp * ff[r, v, m] * fresnel * seen * d * d / (izp + lam_i)


@compiled(parallel=True)
def _select_loop(rows, top, members, wi, ff, drive, wi_c, ff_c, drive_c, out):  # pragma: no cover
    """Fills the packed ``out (N, V, 6, M)`` (see ``selected_emitters``), texel n from row ``rows[n]``
    of the per-sample arrays."""
    N, V, E = top.shape
    C, S = members.shape
    for n in numba.prange(N):
        r = rows[n]
        for v in range(V):
            o = out[n, v]
            j = 0
            for b in range(E):
                for s in range(S):
                    k = members[top[n, v, b], s]
                    f = ff[r, v, k]
                    for i in range(3):
                        o[i, j], o[3 + i, j] = wi[r, v, i, k], f * drive[k, i]
                    j += 1
            for c in range(C):
                expanded = False
                for b in range(E):
                    expanded = expanded or top[n, v, b] == c
                if expanded:
                    continue
                f = ff_c[r, v, c]
                for i in range(3):
                    o[i, j], o[3 + i, j] = wi_c[r, v, i, c], f * drive_c[c, i]
                j += 1


@compiled(parallel=True, fastmath=True)
def _directions_loop(x, frame, live, pts, weights, normals, wo, wi, falloff, cos_l):  # pragma: no cover
    """Fills ``wo, wi`` (see ``emitter_directions``), ``falloff`` without Psi (w_q / r^2, 0 for
    padding entries) and the emitter-side cosine ``cos_l`` clamped to [0, 1]; a padding sample (no
    light, cosine 0) when ``wi`` has K + 1 columns."""
    M, K = x.shape[0], pts.shape[1]
    px, py, pz = pts[0], pts[1], pts[2]
    qx, qy, qz = normals[0], normals[1], normals[2]
    for m in numba.prange(M):
        x0, x1, x2 = x[m, 0], x[m, 1], x[m, 2]
        t0, t1, t2 = frame[m, 0, 0], frame[m, 0, 1], frame[m, 0, 2]
        b0, b1, b2 = frame[m, 1, 0], frame[m, 1, 1], frame[m, 1, 2]
        n0, n1, n2 = frame[m, 2, 0], frame[m, 2, 1], frame[m, 2, 2]
        inv_x = 1.0 / math.sqrt(max(x0 * x0 + x1 * x1 + x2 * x2, 1e-20))
        wo[m, 0] = -(t0 * x0 + t1 * x1 + t2 * x2) * inv_x
        wo[m, 1] = -(b0 * x0 + b1 * x1 + b2 * x2) * inv_x
        wo[m, 2] = -(n0 * x0 + n1 * x1 + n2 * x2) * inv_x
        lit = 1.0 if live[m] else 0.0
        for k in range(K):
            dx, dy, dz = px[k] - x0, py[k] - x1, pz[k] - x2
            r2 = max(dx * dx + dy * dy + dz * dz, 1e-12)
            inv = 1.0 / math.sqrt(r2)
            wi[m, 0, k] = (t0 * dx + t1 * dy + t2 * dz) * inv
            wi[m, 1, k] = (b0 * dx + b1 * dy + b2 * dz) * inv
            wi[m, 2, k] = (n0 * dx + n1 * dy + n2 * dz) * inv
            cos_l[m, k] = min(max(-(dx * qx[k] + dy * qy[k] + dz * qz[k]) * inv, 0.0), 1.0)
            falloff[m, k] = weights[k] / r2 * lit
        if wi.shape[2] > K:  # the padding sample: any direction, no light
            for j in range(3):
                wi[m, j, K] = wi[m, j, 0]
            falloff[m, K], cos_l[m, K] = 0.0, 0.0
