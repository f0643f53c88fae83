"""The photos a registration is judged on (``PhotoStack``: averaged down, blurred, linear), the
scanner's emitters merged into a few lights for their diffuse shading (``shading_lights``), and the
elimination of what Eq. 1 leaves out — each point's albedo and each photo's smooth shading field
(``eliminate_nuisances``).

Convention: linear RGB pixels; camera_from_mesh poses rigid 4x4 (OpenCV axes); the mesh frame in
metres.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import replace

import numpy as np
import torch
import torch.nn.functional as F

from ..io.thread_pools import single_threaded_blas
from ..physics.frame import any_tangent
from ..physics.measurement import local_emitter_geometry, terms_from_lobe
from ..scanner import camera
from ..scanner.scanner import Scanner
from .settings import TUNING

# the per-observation arrays (pixels, residuals, Jacobians): float32 holds a pixel to 1e-4 px and a log
# residual to 1e-7, far below the photos' noise; only the 7 x 7 normal equations are solved in float64
WORK = torch.float32


class PhotoStack:
    """Linear photos ``(V, 3, h, w)`` at a working size, the matching scanner, and their blurs."""

    def __init__(self, codes: Iterable[np.ndarray], scanner: Scanner):
        """``codes``: 8-bit ``(H, W, 3)`` photos of ``scanner``'s camera, taken one at a time (a
        generator keeps one full-size photo in memory, not all of them: 40 of the device's are 4.8 GB
        as float64)."""
        factor = max(1, int(np.ceil(scanner.width / TUNING.stack.max_working_width)))
        self.scanner = camera.resampled(scanner, 1.0 / factor) if factor > 1 else scanner
        linear, usable = [], []
        for c in codes:
            photo = torch.as_tensor(c, dtype=torch.float32).permute(2, 0, 1)[None]
            lin = camera.decode(scanner, photo)
            low, high = TUNING.stack.code_range
            ok = ((photo >= low) & (photo <= high)).all(1, keepdim=True).float()
            if factor > 1:  # area average; a pixel with any clipped source pixel is unusable
                lin = F.avg_pool2d(lin, factor)
                ok = (F.avg_pool2d(ok, factor) > 0.999).float()
            linear.append(lin)
            usable.append(ok)
        self.linear, self.usable = torch.cat(linear), torch.cat(usable)
        self._blurred: dict[float, torch.Tensor] = {}
        self._gradients: dict[float, torch.Tensor] = {}

    def subset(self, index: list[int]) -> PhotoStack:
        """The photos at ``index`` (same working size), blurs not yet taken."""
        out = object.__new__(PhotoStack)
        out.scanner, out.linear, out.usable = self.scanner, self.linear[index], self.usable[index]
        out._blurred, out._gradients = {}, {}
        return out

    def blurred(self, sigma: float) -> torch.Tensor:
        """The photos blurred by a Gaussian of ``sigma`` pixels (cached)."""
        if sigma not in self._blurred:
            r = int(np.ceil(3 * sigma))
            g = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=torch.float32) / sigma) ** 2)
            g = (g / g.sum()).repeat(3, 1, 1)  # (3, 1, 2r + 1)
            x = F.conv2d(F.pad(self.linear, (r, r, 0, 0), mode="replicate"), g[:, :, None, :], groups=3)
            self._blurred[sigma] = F.conv2d(F.pad(x, (0, 0, r, r), mode="replicate"), g[:, :, :, None], groups=3)
        return self._blurred[sigma]

    def gradients(self, sigma: float) -> torch.Tensor:
        """Central-difference gradients of the blurred photos ``(V, 6, h, w)``: per channel d/dcol, d/drow."""
        if sigma not in self._gradients:
            x = F.pad(self.blurred(sigma), (1, 1, 1, 1), mode="replicate")
            gx = (x[:, :, 1:-1, 2:] - x[:, :, 1:-1, :-2]) / 2
            gy = (x[:, :, 2:, 1:-1] - x[:, :, :-2, 1:-1]) / 2
            self._gradients[sigma] = torch.stack([gx, gy], 2).flatten(1, 2)
        return self._gradients[sigma]


def shading_lights(scanner: Scanner, cells: tuple[int, int] = TUNING.stack.shading_cells) -> tuple[Scanner, np.ndarray]:
    """A scanner whose point emitters are the drive-weighted centres of groups of the real ones
    (a grid of ``cells`` over the array's two principal axes), and the groups' summed effective
    pattern ``(G, 3)``: the diffuse term changes slowly across an LED array seen from 0.3 m, so it
    is computed for G groups instead of L emitters (within 0.1% here; ``tests/register/test_photo_stack.py``)."""
    P, p_eff = scanner.emitter_positions, scanner.effective_pattern()
    centre = P.mean(0)
    axes = np.linalg.svd(P - centre)[2][:2]
    coords = (P - centre) @ axes.T
    lo, hi = coords.min(0), coords.max(0) + 1e-12
    cell = np.minimum(((coords - lo) / (hi - lo) * cells).astype(int), np.array(cells) - 1)
    group = cell[:, 0] * cells[1] + cell[:, 1]
    drive = p_eff.sum(1) + 1e-12
    ids = np.unique(group)
    pos, nrm, eff = [], [], []
    for g in ids:
        m = group == g
        pos.append((P[m] * drive[m, None]).sum(0) / drive[m].sum())
        nrm.append(scanner.emitter_normals[m].mean(0))
        eff.append(p_eff[m].sum(0))
    normals = np.array(nrm) / np.linalg.norm(nrm, axis=1, keepdims=True)
    lights = replace(
        scanner,
        emitter_kind="point",
        emitter_positions=np.array(pos),
        emitter_normals=normals,
        emitter_axes=np.array([any_tangent(torch.as_tensor(nn)).numpy() for nn in normals]),
        quadrature=(1, 1),
        pattern=np.zeros((len(ids), 3)),
        grid_shape=None,
    )
    return lights, np.array(eff)


def diffuse_shading(
    scanner: Scanner, x: np.ndarray, n: np.ndarray, groups: tuple[Scanner, np.ndarray] | None = None, chunk: int = 16384
) -> np.ndarray:
    """D ``(M, 3)``: the rho_d = 1 measurement of camera-space points ``x`` with normals ``n``
    (``groups``: ``shading_lights(scanner)`` when already at hand)."""
    lights, p_eff = groups if groups is not None else shading_lights(scanner)
    p_eff_t = torch.as_tensor(p_eff, dtype=WORK)
    out = np.zeros((len(x), 3))
    for a in range(0, len(x), chunk):
        xt = torch.as_tensor(x[a : a + chunk], dtype=WORK)
        nt = torch.as_tensor(n[a : a + chunk], dtype=WORK)
        geo = local_emitter_geometry(lights, xt, nt, any_tangent(nt))
        a_l, _ = terms_from_lobe(geo, torch.zeros_like(geo.falloff))
        out[a : a + chunk] = (a_l @ p_eff_t).numpy() / np.pi
    return out * scanner.exposure()


def edge_mask(hit: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Pixels ``(h, w)`` beside a pixel that misses the mesh while they hit it (or the reverse), or
    whose depth differs by more than 2%: the silhouette and the depth edges of the mesh's image."""
    d = np.where(hit, depth, 0.0)
    edge = np.zeros_like(hit)
    for axis in (0, 1):
        a, b = [slice(None)] * 2, [slice(None)] * 2
        a[axis], b[axis] = slice(1, None), slice(None, -1)
        jump = (hit[tuple(a)] != hit[tuple(b)]) | (np.abs(d[tuple(a)] - d[tuple(b)]) > 0.02 * d[tuple(a)])
        edge[tuple(a)] |= jump
        edge[tuple(b)] |= jump
    return edge


def eliminate_nuisances(field: torch.Tensor, w: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``x`` less its weighted least-squares fit by the nuisances of the photometric cost: a log
    albedo per surface point and channel, and per photo and channel a shading field
    ``sum_k b_jk field[p, k]``.

    Convention: ``x (V, N, 3, C)`` log values of V photos x N points x RGB, C columns fitted alike
    (residuals, Jacobian columns); ``w (V, N, 3)`` the weights, 0 where unobserved; ``field (N, K)``
    the fields' basis at the points (K = 0: albedos only). The result is ``x``'s weighted residual
    (where ``w`` is 0 it is not meaningful). The fields are known up to one field common to all
    photos (the albedos absorb it): a tiny ridge picks one, which leaves the residual unchanged.
    Where ``w`` is 0, ``x`` may be infinite: it does not enter.
    """
    # 0 * inf would be NaN: unobserved entries are zeroed where any is not finite (a sum tells, and
    # costs far less than the masked copy)
    if not bool(torch.isfinite(x.sum())):
        x = torch.where(w[..., None] > 0, x, torch.zeros((), dtype=x.dtype))
    (V, N, _), K, C = w.shape, field.shape[1], x.shape[-1]
    wsum = w.sum(0).clamp_min(1e-12)  # (N, 3)
    share = w / wsum  # photo j's weight share in point p's albedo
    # x's big arrays are touched as few times as can be (the cost is their memory traffic): the
    # albedos (share-weighted means over the photos) accumulated photo by photo, no (V, N, 3, C) temporary
    albedo = _photo_mean(share, x)  # (N, 3, C)
    if K == 0:
        return x - albedo[None]
    # normal equations of the fields b (V K unknowns per channel) with the albedos eliminated:
    # sum_p w_jp phi_pk phi_pl (delta_ij - share_ip), solved in float64 (V K is a few hundred)
    wc = w.permute(2, 1, 0)  # (3, N, V)
    # rows w_jp phi_pk / sqrt(wsum_p), built contiguous (the strided broadcast was 2-4x slower)
    A = ((w * wsum.rsqrt()).permute(2, 1, 0).contiguous()[..., None] * field[:, None, :]).reshape(3, N, V * K)
    M = -(A.transpose(1, 2) @ A).double()
    own = (wc.transpose(1, 2) @ (field[:, :, None] * field[:, None, :]).reshape(N, K * K)).reshape(3, V, K, K)
    photo = torch.arange(V)
    M.view(3, V, K, V, K)[:, photo, :, photo, :] += own.double().permute(1, 0, 2, 3)
    ridge = 1e-6 * torch.diagonal(M, dim1=1, dim2=2).mean(1) + 1e-12
    M += ridge[:, None, None] * torch.eye(V * K, dtype=torch.float64)
    # right-hand sides sum_p w_jp (x_jp - albedo_p) phi_pk: photo by photo over x (V, N, 3 C), less
    # the albedos' part per channel
    own_rhs = (field.T[None] @ (w[..., None] * x).reshape(V, N, 3 * C)).reshape(V, K, 3, C)
    albedo_phi = (albedo[:, :, None, :] * field[:, None, :, None]).reshape(N, 3, K * C).permute(1, 0, 2)
    rhs = own_rhs.permute(2, 0, 1, 3) - (w.permute(2, 0, 1) @ albedo_phi).reshape(3, V, K, C)
    # numpy's LU, not torch's: torch 2.13's batched float64 solve of these sizes (V K >= ~160) fails
    # with bogus pivots once torch.set_num_threads has been called (--threads; measured); OpenBLAS on
    # one thread, or it fights torch's threads (io.thread_pools)
    with single_threaded_blas():
        b_np = np.linalg.solve(M.numpy(), rhs.reshape(3, V * K, C).double().numpy())
    b = torch.from_numpy(b_np).to(x.dtype).reshape(3, V, K, C)
    # x - albedo - f + (f's own albedo), f_jp = sum_k phi_pk b_jk: f built photo-major, then in place
    f = (field[None] @ b.permute(1, 2, 0, 3).reshape(V, K, 3 * C)).reshape(V, N, 3, C)
    f += (albedo - _photo_mean(share, f))[None]
    return torch.sub(x, f, out=f)


def _photo_mean(share: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``sum_j share[j, ..., None] * x[j]``: ``share (V, N, 3)``, ``x (V, N, 3, C)`` -> ``(N, 3, C)``,
    accumulated photo by photo (one read of ``x``, no temporary of its size)."""
    out = torch.zeros(x.shape[1:], dtype=x.dtype)
    for j in range(len(x)):
        out.addcmul_(share[j, ..., None], x[j])
    return out
