"""Light the support reflects onto the object: the refinement's second light source (issue 17).

The scanner's LEDs light the table the object stands on as much as the object, and a glossy face
seen edge-on mirrors that table into the camera. Eq. 1 (direct light only) lacks this light; the
refinement then explains it by turning lobes toward the LEDs (Cycles scans: normals tilted up by
Δn_z 0.02–0.08, a blob's brushed underside |log rho_s| 8.5 — docs/history/accuracy.md).

Model: the support is the plane z = ``SupportAlbedo.z`` of the mesh frame (``scan.support_plane``:
the mesh's lowest z), Lambertian, with an albedo map read from the photos themselves
(``estimate_support_albedo``: each photo's support pixels over the irradiance the scanner's
emitters give there, the median over the photos). In photo j its radiance at p is
a(p) / pi * E_j(p), E_j the pattern's irradiance from the scanner's emitters (their blocks'
coarse emitters: the support is far from them compared with a block), zero where the object hides
the scanner from p (one ray toward the camera: the emitters sit beside it). Toward a texel that is
an area light, summed by Monte Carlo over fixed, stratified sample directions per entry (a lattice
shifted by a hash of the entry's point: ``entry_shifts``) — from the
normals of the round's lobe (widened) visible from the camera (specular; Heitz 2018), and
cosine-distributed about the geometric normal (diffuse) — each one more emitter of the refinement
with that photo's radiance as its drive and 1 / (S pdf) as its falloff; a direction that does not
reach the support within ``TUNING.support.max_reach``, or that the object blocks, carries none. For fixed
directions the sums are smooth in the parameters, so the refinement's Jacobians hold; each round
draws them again for its lobe.

Convention: per texel, its world position ``position (N, 3)`` (mesh frame, metres) and geometric
frame ``frame_world (N, 3, 3)`` (rows t^, b^, n^ in the mesh frame); per entry its camera-space
point ``x_cam (N, V, 3)`` and geometric frame ``frame_cam (N, V, 3, 3)`` (the trace's columns);
directions and results in the texel's geometric frame (as ``pixel_bases``), drives in linear pixel
units with the exposure (as the emitters').

The object's light on itself (``SupportScene.face_albedo``): a concave object lights itself — the
emitters light one face, which reflects onto another, and the refinement explained that light by
bending lobes (the gallery's knot under Cycles: its glossy plastic's width fell to the 0.006
floor; rendered without bounces, it came back right — docs/history/accuracy.md). A sample direction that
meets the mesh before the support (and within ``TUNING.support.max_reach``) carries the radiance of the point p
it meets: one diffuse bounce, rho_d(p) / pi * E_j(p), rho_d the current answer's albedo of p's
triangle (``face_albedo``), E_j as the support's, zero where p's face looks away from the texel
or the mesh hides the camera from p. What p's lobe reflects of the emitters (sharp, and only as
right as the lobe's estimate) is left out.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from ..io.maps import bilinear_pixels
from ..io.raycast import RayCaster
from ..physics.brdf import ALPHA_MAX, F0_DIELECTRIC, bounded_f90, fresnel_schlick, ggx_ndf, smith_g1
from ..physics.emitter_blocks import EmitterBlocks, emitter_blocks
from ..scanner import camera
from ..scanner.scanner import Scanner
from .settings import TUNING


@dataclass(frozen=True)
class SupportAlbedo:
    """The support's diffuse albedo on the plane z = ``z``: a map of square cells (cell (i, j)
    covers x in origin_x + [j, j + 1) cell, y in origin_y + [i, i + 1) cell), ``fill`` beyond it."""

    z: float
    origin: np.ndarray  # (2,) m
    cell: float  # m
    albedo: np.ndarray  # (H, W, 3)
    fill: np.ndarray  # (3,)

    def at(self, xy: Tensor) -> Tensor:
        """Albedo ``(..., 3)`` at world ``xy (..., 2)`` (nearest cell), in ``xy``'s dtype."""
        H, W, _ = self.albedo.shape
        ij = torch.floor((xy - torch.as_tensor(self.origin, dtype=xy.dtype)) / self.cell).long()
        col, row = ij[..., 0], ij[..., 1]
        inside = (col >= 0) & (col < W) & (row >= 0) & (row < H)
        table = torch.cat(
            [
                torch.as_tensor(self.albedo, dtype=xy.dtype).reshape(-1, 3),
                torch.as_tensor(self.fill, dtype=xy.dtype)[None],
            ]
        )
        flat = torch.where(inside, row.clamp(0, H - 1) * W + col.clamp(0, W - 1), H * W)
        return table[flat]

    def save(self, path: Path) -> None:
        """As one ``.npz``."""
        np.savez(path, z=self.z, origin=self.origin, cell=self.cell, albedo=self.albedo, fill=self.fill)

    @classmethod
    def load(cls, path: Path) -> SupportAlbedo:
        """What ``save`` wrote."""
        with np.load(path) as f:
            return cls(float(f["z"]), f["origin"], float(f["cell"]), f["albedo"], f["fill"])


@dataclass(frozen=True)
class SupportScene:
    """What the refinement needs of the support: its albedo and, where given, the object's mesh
    as a ray caster (what it hides from the texels and the scanner; None: nothing hidden). With
    the caster, the mesh's unit ``face_normal (F, 3)`` and ``face_albedo (F, 3)`` (triangles in
    the caster's order): the object's light on itself too (module docstring). ``exposed (T,)``:
    per texel of the atlas, whether the whole mesh lies behind its tangent plane (``exposed``;
    None: not known) — its rays that leave above the plane are not cast."""

    albedo: SupportAlbedo
    caster: RayCaster | None = None
    face_normal: np.ndarray | None = None
    face_albedo: np.ndarray | None = None
    exposed: np.ndarray | None = None


def exposed(vertices: np.ndarray, position: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """``(T,)`` bool: no corner of the mesh (``vertices (P, 3)``, m) lies more than TUNING.support.ray_offset / 2
    above the tangent plane of each texel at ``position (T, 3)`` with unit geometric ``normal (T,
    3)`` (one frame for all). Then no ray that leaves such a texel above its plane (from TUNING.support.ray_offset
    off it) meets the mesh — each triangle lies within its corners' hull — and none is cast: every
    texel of a convex object (the gallery's dome), 75 / 48 / 32 / 12% of the box's (its edges'
    interpolated normals lean over the next face), vase's, blob's, knot's."""
    v = torch.as_tensor(vertices, dtype=torch.float64)
    out = np.zeros(len(position), bool)
    for s in range(0, len(position), 1024):  # (P, 1024) heights at a time
        p, n = torch.as_tensor(position[s : s + 1024]).double(), torch.as_tensor(normal[s : s + 1024]).double()
        height = v @ n.T - (p * n).sum(-1)  # (P, chunk) m above each tangent plane
        out[s : s + len(p)] = (height.amax(0) <= 0.5 * TUNING.support.ray_offset).numpy()
    return out


def face_albedo(face_count: int, texel_face: np.ndarray, rho_d: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Per triangle ``(F, 3)`` the mean ``rho_d (T, 3)`` of its ``known (T,)`` texels (``texel_face
    (T,)``: each texel's triangle); a triangle with none takes the known texels' median (0 with
    none known)."""
    face, values = texel_face[known], np.asarray(rho_d, np.float64)[known]
    count = np.bincount(face, minlength=face_count).astype(np.float64)
    total = np.stack([np.bincount(face, values[:, c], minlength=face_count) for c in range(3)], 1)
    fill = np.median(values, 0) if len(values) else np.zeros(3)
    return np.where(count[:, None] > 0, total / np.maximum(count, 1.0)[:, None], fill)


class SupportView(NamedTuple):
    """The support as N texels see it: the scene, their world ``position (N, 3)`` and geometric
    ``frame_world (N, 3, 3)`` (rows t^, b^, n^ in the mesh frame), and where known which are
    ``exposed (N,)`` (``SupportScene.exposed``)."""

    scene: SupportScene
    position: Tensor
    frame_world: Tensor
    exposed: Tensor | None = None

    def rows(self, idx: Tensor) -> SupportView:
        """The same view of the texels ``idx`` only."""
        exposed = None if self.exposed is None else self.exposed[idx]
        return SupportView(self.scene, self.position[idx], self.frame_world[idx], exposed)


class Sources(NamedTuple):
    """The emitters that light the support, in camera space: ``points, normals (C, 3)`` and the
    effective drive ``(C, 3)`` with their quadrature weights (Psi as the scanner's)."""

    points: Tensor
    normals: Tensor
    drive: Tensor

    @classmethod
    def of(cls, scanner: Scanner, blocks: EmitterBlocks | None = None) -> Sources:
        """``scanner``'s emitter blocks' coarse emitters (every sample on a small device);
        ``blocks``: its ``emitter_blocks``, where the caller has them already."""
        blocks = blocks or emitter_blocks(scanner)
        if blocks is not None:
            c = blocks.coarse
            return cls(
                torch.as_tensor(c.emitter_positions), torch.as_tensor(c.emitter_normals), blocks.coarse_drive.double()
            )
        pts, w = scanner.emitter_samples(torch.float64)
        L, Q = w.shape
        drive = torch.as_tensor(scanner.effective_pattern()).repeat_interleave(Q, 0) * w.reshape(-1, 1)
        normals = torch.as_tensor(scanner.emitter_normals).repeat_interleave(Q, 0)
        return cls(pts.reshape(-1, 3), normals, drive)


def irradiance(scanner: Scanner, sources: Sources, points: Tensor, normal: Tensor) -> Tensor:
    """Pattern irradiance ``(M, 3)`` float64 (linear pixel units of a unit-albedo Lambertian surface
    times pi, exposure included) at camera-space ``points (M, 3)`` with unit ``normal (M, 3)``,
    unshadowed. Summed in float32, as matmuls (|s - p|^2 = |s|^2 - 2 p.s + |p|^2): 18x faster than
    float64 (m, C, 3) temporaries, within 3e-5 of them at the scanner's distances (~0.1-1 m) — a
    light the refinement takes as data, known to a few % (docs/history/accuracy.md)."""
    f32 = torch.float32
    out = torch.zeros(len(points), 3, dtype=torch.float64)
    exposure = float(scanner.exposure(scanner.pattern))
    s_pts, s_nrm, drive = sources.points.to(f32), sources.normals.to(f32), sources.drive.to(f32)
    s_sq, s_self = (s_pts * s_pts).sum(-1), (s_pts * s_nrm).sum(-1)
    for s in range(0, len(points), 1 << 16):  # (chunk, C) temporaries stay ~10 MB
        p, n = points[s : s + (1 << 16)].to(f32), normal[s : s + (1 << 16)].to(f32)
        inv = torch.addmm(s_sq + (p * p).sum(-1, keepdim=True), p, s_pts.T, alpha=-2.0).clamp_min_(1e-12).rsqrt_()
        cos_s = torch.addmm(-(p * n).sum(-1, keepdim=True), n, s_pts.T).mul_(inv).clamp_min_(0.0)
        cos_e = torch.addmm(-s_self.expand(len(p), -1), p, s_nrm.T).mul_(inv)
        w = scanner.psi(cos_e).mul_(cos_s).mul_(inv.square_())  # (m, C): Psi cos_s / r^2
        out[s : s + len(p)] = exposure * (w @ drive).double()
    return out


def _stratified(count: int, shift: Tensor) -> Tensor:
    """``count`` points ``(..., count, 2)`` in the unit square: a Fibonacci lattice moved by each
    ``shift (..., 2)`` (modulo 1; a Cranley-Patterson rotation)."""
    i = torch.arange(count, dtype=torch.float64)
    lattice = torch.stack([(i + 0.5) / count, torch.remainder(i * 0.6180339887498949 + 0.5, 1.0)], -1)
    return torch.remainder(lattice + shift.to(torch.float64)[..., None, :], 1.0)


def entry_shifts(x_cam: Tensor) -> Tensor:
    """Each entry's own lattice shift ``(N, V, 2)`` in [0, 1): a hash of its camera-space point
    ``x_cam (N, V, 3)`` (metres), so fixed for the entry whatever chunk or round it is summed in.
    Why: one lattice for every entry errs the same way on all of them — its sums over a material
    moved by -7% to +7% as the lattice was shifted (the box's Cycles metals), a bias no number of
    entries averages out; shifted per entry, the errors differ and do."""
    x, y, z = x_cam.to(torch.float64).unbind(-1)  # elementwise (a matmul's sums vary with the batch's shape)
    a = torch.sin((12.9898 * x + 78.233 * y + 37.719 * z) * 100.0) * 43758.5453
    b = torch.sin((39.3468 * x + 11.135 * y + 83.155 * z) * 100.0) * 24634.6345
    return torch.stack([torch.remainder(a, 1.0), torch.remainder(b, 1.0)], -1)


def visible_half_vectors(wo: Tensor, alpha: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
    """Half vectors ``(N, V, S, 3)`` (shading frame) distributed as GGX's normals visible from
    ``wo (N, V, 3)`` (Heitz 2018) for ``alpha (N, 2)``, from unit-square points ``u (S, 2)``, and the
    density of the reflected direction ``(N, V, S)``: G1(wo) D(h) / (4 wo_z) per steradian of wi
    (0 where wo_z <= 0). Its weights f cos_i / pdf stay below F G1(wi) for the sampled alphas. ``u``
    may also be one set per entry ``(N, V, S, 2)``."""
    ax, ay = alpha[:, None, None, 0], alpha[:, None, None, 1]
    o = wo[:, :, None]
    vh = torch.stack([ax * o[..., 0], ay * o[..., 1], o[..., 2].clamp_min(1e-6)], -1)
    vh = vh / vh.norm(dim=-1, keepdim=True)
    lensq = vh[..., 0] ** 2 + vh[..., 1] ** 2
    inv = torch.where(lensq > 1e-12, torch.rsqrt(lensq.clamp_min(1e-12)), torch.zeros_like(lensq))
    t1 = torch.stack([-vh[..., 1] * inv, vh[..., 0] * inv, torch.zeros_like(lensq)], -1)
    t1 = torch.where((lensq > 1e-12)[..., None], t1, torch.tensor([1.0, 0.0, 0.0], dtype=wo.dtype))
    t2 = torch.linalg.cross(vh, t1)
    r, phi = torch.sqrt(u[..., 0]), 2 * math.pi * u[..., 1]
    p1, p2 = r * torch.cos(phi), r * torch.sin(phi)
    s = 0.5 * (1.0 + vh[..., 2])
    p2 = (1.0 - s) * torch.sqrt((1.0 - p1**2).clamp_min(0.0)) + s * p2
    p3 = torch.sqrt((1.0 - p1**2 - p2**2).clamp_min(0.0))
    nh = p1[..., None] * t1 + p2[..., None] * t2 + p3[..., None] * vh
    h = torch.stack([ax * nh[..., 0], ay * nh[..., 1], nh[..., 2].clamp_min(0.0)], -1)
    h = h / h.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    oz = o[..., 2]
    pdf = torch.where(oz > 0, smith_g1(o, ax, ay) * ggx_ndf(h, ax, ay) / (4 * oz.clamp_min(1e-6)), torch.zeros_like(oz))
    return h, pdf


def cosine_directions(u: Tensor) -> tuple[Tensor, Tensor]:
    """Directions ``(..., S, 3)`` (shading frame) distributed as cos(theta) / pi from ``u (..., S,
    2)``, and that density ``(..., S)``."""
    r, phi = torch.sqrt(u[..., 0]), 2 * math.pi * u[..., 1]
    z = torch.sqrt((1.0 - u[..., 0]).clamp_min(1e-12))
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1), z / math.pi


class SupportEmitters(NamedTuple):
    """Entries' specular support samples as the refinement's emitters (geometric frame): ``wi (N, V,
    S, 3)``, ``weight (N, V, S)`` (the sample's, in the place of an emitter's falloff; Fresnel is the
    pixel bases' own), ``drive (N, V, S, 3)`` (``pixel_bases.pack_emitters``' inputs)."""

    wi: Tensor
    weight: Tensor
    drive: Tensor


def support_diffuse_basis(
    view: SupportView, scanner: Scanner, sources: Sources, x_cam: Tensor, frame_cam: Tensor, live: Tensor
) -> Tensor:
    """The support's light on the entries of ``view``'s N texels as a diffuse basis ``(N, V, 3, 3)``
    (``pixel_bases``' layout; module docstring), ``live (N, V)`` the entries that count: sampled
    about the geometric normal, once for every round (a shading normal a few degrees off changes
    which samples lie above its horizon by as little), in ``x_cam``'s dtype."""
    f64 = torch.float64
    # geometric frame: about n^ = z, each entry's own lattice
    omega, d_pdf = cosine_directions(_stratified(TUNING.support.diffuse_samples, entry_shifts(x_cam)))  # (N, V, Sd, 3)
    position, frame_world = view.position.to(f64), view.frame_world.to(f64)
    radiance = _radiance(
        view.scene, scanner, sources, position, frame_world, x_cam, frame_cam, live, omega, view.exposed
    )
    lit = radiance * (1.0 / (TUNING.support.diffuse_samples * math.pi * d_pdf))[..., None]  # (N, V, Sd, 3)
    return torch.einsum("nvsc,nvsj->nvcj", lit, omega).to(x_cam.dtype)


def support_specular_emitters(
    view: SupportView,
    scanner: Scanner,
    sources: Sources,
    x_cam: Tensor,
    frame_cam: Tensor,
    live: Tensor,
    wo: Tensor,
    frame0: Tensor,
    alpha: Tensor,
    rho_s: Tensor | None = None,
) -> SupportEmitters:
    """The support's light on the entries of ``view``'s N texels as specular emitters (module
    docstring): ``live (N, V)``, ``wo (N, V, 3)`` toward the camera, the round's shading frame
    ``frame0 (N, 3, 3)`` and lobe ``alpha (N, 2)``; in ``wo``'s dtype. With the lobe's ``rho_s (N,
    3)`` the light reflects with the bounded Fresnel (``physics.brdf.bounded_f90``: the emitters'
    radiance times its F over the BRDF's, per sample's w_i.h)."""
    f64 = torch.float64
    wo_, f0 = wo.to(f64), frame0.to(f64)
    wide = (TUNING.support.sample_widen * alpha.to(f64)).clamp(TUNING.support.sample_floor, ALPHA_MAX)
    wo_loc = (f0[:, None] @ wo_[..., None])[..., 0]  # shading frame (N, V, 3)
    h_loc, pdf = visible_half_vectors(wo_loc, wide, _stratified(TUNING.support.specular_samples, entry_shifts(x_cam)))
    halves = h_loc @ f0[:, None]  # (N, V, Ss, 3) geometric frame
    o_h = (wo_[:, :, None] * halves).sum(-1)
    wi = 2 * o_h[..., None] * halves - wo_[:, :, None]
    usable = (o_h > 0) & (pdf > 0)
    weight = torch.where(usable, 1.0 / (TUNING.support.specular_samples * pdf.clamp_min(1e-30)), 0.0)
    position, frame_world = view.position.to(f64), view.frame_world.to(f64)
    live = live & usable.any(-1)
    radiance = _radiance(view.scene, scanner, sources, position, frame_world, x_cam, frame_cam, live, wi, view.exposed)
    if rho_s is not None:  # w_i.h = wo.h: wi is wo mirrored about h
        c = o_h[..., None]
        f90 = bounded_f90(rho_s.to(f64))[:, None, None, :]
        radiance = radiance * fresnel_schlick(c, F0_DIELECTRIC, f90) / fresnel_schlick(c, F0_DIELECTRIC)
    dt = wo.dtype
    return SupportEmitters(wi.to(dt), weight.to(dt), radiance.to(dt))


def _radiance(
    scene: SupportScene,
    scanner: Scanner,
    sources: Sources,
    position: Tensor,
    frame_world: Tensor,
    x_cam: Tensor,
    frame_cam: Tensor,
    live: Tensor,
    omega: Tensor,
    exposed: Tensor | None = None,
) -> Tensor:
    """The support's radiance ``(N, V, S, 3)`` toward each entry's texel along ``omega (N, V, S, 3)``
    (geometric frame): 0 where the direction misses the support (or the object is in the way),
    the object's own where ``scene`` has its ``face_albedo`` and the direction meets it first.
    One ray per live sample finds what it meets first (the mesh's face or, beyond it, the support
    point; none where the texel is ``exposed (N,)`` and the sample leaves above its plane), one
    more whether that point sees the camera."""
    f64 = torch.float64
    N, V, S = omega.shape[:3]
    up = frame_world[:, :, 2]  # world z in the texel's frame (N, 3)
    height = (position[:, 2] - scene.albedo.z).clamp_min(TUNING.support.ray_offset)
    down = -(omega * up[:, None, None]).sum(-1)
    reach = height[:, None, None] / down.clamp_min(1e-9)
    out = torch.zeros(N, V, S, 3, dtype=f64)
    support = (down > 1e-3) & (reach < TUNING.support.max_reach) & live[..., None]
    cast = live[..., None].expand(N, V, S)
    if exposed is not None:  # nothing of the mesh above these texels' planes (``exposed``): no ray
        # that stays above TUNING.support.ray_offset / 2 up to the support point (or all along) can meet it
        above = torch.where(support, reach * omega[..., 2] >= 0.5 * TUNING.support.ray_offset, omega[..., 2] > 0)
        cast = cast & ~(exposed[:, None, None] & above)
    sel = cast.nonzero(as_tuple=True)
    if scene.caster is not None and len(sel[0]):  # the mesh's first face along each cast sample
        # each ray leaves TUNING.support.ray_offset off the surface; one that reaches the support aims at its point
        # there (along omega from the offset start it slipped past the object's edge where it meets
        # the support, lighting points under the Cycles vase's rim)
        aim, to_table, reaches = omega[sel].to(f64), reach[sel], support[sel]
        aim[:, 2] -= torch.where(reaches, TUNING.support.ray_offset / to_table, 0.0)
        to_point = to_table * aim.norm(dim=-1)  # from the ray's start to the support point
        aim = aim / aim.norm(dim=-1, keepdim=True)
        t, prim = _first_hits(scene, position[sel[0]], frame_world[sel[0]], aim)
        support[sel] = reaches & (t >= to_point - TUNING.support.ray_offset)  # the object hides the support point
        if scene.face_albedo is not None:
            _object_radiance(
                scene, scanner, sources, position, frame_world, x_cam, frame_cam, aim, reach, out, sel, t, prim
            )
    sel = support.nonzero(as_tuple=True)
    n, v = sel[0], sel[1]
    if len(n) == 0:
        return out
    p_loc = reach[sel][:, None] * omega[sel].to(f64)  # texel -> support point, geometric frame (M, 3)
    fw, fc, xc = frame_world[n], frame_cam[n, v].to(f64), x_cam[n, v].to(f64)
    p_world = position[n] + (p_loc[:, None] @ fw)[:, 0]
    keep = torch.ones(len(n), dtype=torch.bool)
    if scene.caster is not None:
        keep = ~_camera_hidden(scene.caster, position[n], fw, xc, fc, p_world)
    p_cam = xc + (p_loc[:, None] @ fc)[:, 0]
    up_cam = (up[n][:, None] @ fc)[:, 0]
    e = irradiance(scanner, sources, p_cam[keep], up_cam[keep])
    out[tuple(i[keep] for i in sel)] = scene.albedo.at(p_world[keep, :2]) / math.pi * e
    return out


def _object_radiance(
    scene: SupportScene,
    scanner: Scanner,
    sources: Sources,
    position: Tensor,
    frame_world: Tensor,
    x_cam: Tensor,
    frame_cam: Tensor,
    aim: Tensor,
    reach: Tensor,
    out: Tensor,
    sel: tuple[Tensor, ...],
    t: Tensor,
    prim: Tensor,
) -> None:
    """Writes into ``out (N, V, S, 3)`` the object's radiance toward each entry's texel where the ray
    of its sample ``sel`` (M of them; unit ``aim (M, 3)``, geometric frame, from TUNING.support.ray_offset off the
    texel) first meets the mesh's face ``prim (M,)`` at ``t (M,)`` (``_first_hits``) before the
    support (``reach (N, V, S)``, m): one diffuse bounce (module docstring; the other arguments
    ``_radiance``'s). Only the exact test of ``exposed`` leaves a sample without its ray: 64
    directions uniform over the hemisphere, as a coarser probe, missed 2,180 of the 8,064 gallery
    vase texels that see the vase in 1,024 (its slivers at grazing angles)."""
    assert scene.caster is not None and scene.face_normal is not None and scene.face_albedo is not None
    f64 = torch.float64
    n, v = sel[0], sel[1]
    k = ((prim >= 0) & (t < reach[sel].clamp_max(TUNING.support.max_reach))).nonzero().squeeze(1)
    if len(k) == 0:
        return
    n, v, fw = n[k], v[k], frame_world[n[k]]
    xc, fc = x_cam[n, v].to(f64), frame_cam[n, v].to(f64)
    p_world = position[n] + TUNING.support.ray_offset * fw[:, 2] + t[k, None] * (aim[k][:, None] @ fw)[:, 0]
    # the camera (and the emitters beside it) seen from p; p itself is the ray's first hit
    seen = ~_camera_hidden(scene.caster, position[n], fw, xc, fc, p_world)
    k, n, v, fw, xc, fc, p_world = k[seen], n[seen], v[seen], fw[seen], xc[seen], fc[seen], p_world[seen]
    if len(k) == 0:
        return
    # p and its face's normal in the entry's camera frame (mesh frame -> texel frame -> camera)
    normal = torch.as_tensor(scene.face_normal, dtype=f64)[prim[k]]
    p_cam = xc + ((fw @ (p_world - position[n])[..., None])[..., 0][:, None] @ fc)[:, 0]
    normal_cam = ((fw @ normal[..., None])[..., 0][:, None] @ fc)[:, 0]
    e = irradiance(scanner, sources, p_cam, normal_cam)
    albedo = torch.as_tensor(scene.face_albedo, dtype=f64)[prim[k]]
    out[tuple(i[k] for i in sel)] = albedo / math.pi * e


def _first_hits(scene: SupportScene, position: Tensor, frame_world: Tensor, omega: Tensor) -> tuple[Tensor, Tensor]:
    """Where rays from texels at world ``position (M, 3)`` (geometric frames ``frame_world (M, 3,
    3)``) along ``omega (M, 3)`` (that frame) first meet the mesh: the distance ``t (M,)`` (m; ~1e37
    for none) and the triangle ``(M,)`` if it looks back at them (-1: none, or a back face)."""
    assert scene.caster is not None
    d_world = (omega[:, None] @ frame_world)[:, 0]
    hits = scene.caster.intersect((position + TUNING.support.ray_offset * frame_world[:, 2]).numpy(), d_world.numpy())
    prim = torch.from_numpy(np.where(hits.geom >= 0, hits.prim, -1))
    if scene.face_normal is not None:
        normal = torch.as_tensor(scene.face_normal, dtype=d_world.dtype)[prim.clamp_min(0)]
        prim[(normal * d_world).sum(-1) >= 0] = -1  # a back face: the inside of the mesh
    return torch.from_numpy(hits.t), prim


def _camera_hidden(
    caster: RayCaster, position: Tensor, frame_world: Tensor, x_cam: Tensor, frame_cam: Tensor, p_world: Tensor
) -> Tensor:
    """``(M,)`` bool: the mesh lies between the point ``p_world (M, 3)`` a texel at world ``position
    (M, 3)`` (geometric frame ``frame_world (M, 3, 3)``) sees and the camera of the entry (``x_cam``,
    ``frame_cam``: the texel's point and frame in camera space) — the scanner's light: its emitters
    sit beside the camera."""
    camera_loc = -(frame_cam @ x_cam[..., None])[..., 0]  # camera centre, geometric frame (M, 3)
    to_cam = position + (camera_loc[:, None] @ frame_world)[:, 0] - p_world
    cam_dist = to_cam.norm(dim=-1).clamp_min(1e-12)
    to_cam = to_cam / cam_dist[:, None]
    far = (cam_dist - 2 * TUNING.support.ray_offset).clamp_min(0.0)
    return torch.from_numpy(
        caster.occluded((p_world + TUNING.support.ray_offset * to_cam).numpy(), to_cam.numpy(), far.numpy())
    )


def estimate_support_albedo(
    photos: Iterable[tuple[np.ndarray, np.ndarray]],
    poses: list[np.ndarray],
    scanner: Scanner,
    vertices: np.ndarray,
    caster: RayCaster | None,
) -> SupportAlbedo:
    """The support's albedo map under the object standing on z = min z of ``vertices (P, 3)``,
    from ``photos`` (pairs of ``(H, W, 3)`` linear pixels and their 8-bit codes, read once, one at a
    time) with camera-from-world ``poses (4, 4)``: per cell
    and photo that sees the cell's centre (in the photo, in front, not hidden by the mesh, codes in
    ``TUNING.support.code_range``) pi y / E, the median over the photos; cells no photo saw take the median of the
    others (``fill`` too)."""
    z = float(vertices[:, 2].min())
    lo, hi = vertices[:, :2].min(0), vertices[:, :2].max(0)
    centre = 0.5 * (lo + hi)
    half = TUNING.support.reach_radii * 0.5 * float(np.linalg.norm(hi - lo)) + TUNING.support.cell
    n = int(math.ceil(2 * half / TUNING.support.cell))
    origin = centre - 0.5 * n * TUNING.support.cell
    jj, ii = np.meshgrid(np.arange(n), np.arange(n))
    cells = np.stack(
        [
            origin[0] + (jj + 0.5) * TUNING.support.cell,
            origin[1] + (ii + 0.5) * TUNING.support.cell,
            np.full((n, n), z),
        ],
        -1,
    ).reshape(-1, 3)
    sources = Sources.of(scanner)
    samples = []
    for (linear, codes), pose in zip(photos, poses):
        R, t = pose[:3, :3], pose[:3, 3]
        p_cam = cells @ R.T + t
        value = np.full((len(cells), 3), np.nan)
        front = p_cam[:, 2] > 1e-3
        px = np.full((len(cells), 2), -1.0)
        px[front] = camera.project(scanner, torch.as_tensor(p_cam[front])).numpy()
        ok = front & camera.in_image(scanner, px)
        if caster is not None and ok.any():
            centre_w = -R.T @ t
            d = centre_w - cells[ok]
            dist = np.linalg.norm(d, axis=1)
            start = cells[ok] + TUNING.support.ray_offset * d / dist[:, None]
            ok[np.nonzero(ok)[0][caster.occluded(start, d / dist[:, None], dist - 2 * TUNING.support.ray_offset)]] = (
                False
            )
        idx = np.nonzero(ok)[0]
        if len(idx):
            code = bilinear_pixels(codes.astype(np.float64), px[idx, 1], px[idx, 0])
            y = bilinear_pixels(linear.astype(np.float64), px[idx, 1], px[idx, 0])
            good = ((code > TUNING.support.code_range[0]) & (code < TUNING.support.code_range[1])).all(1)
            up = np.tile(R[:, 2], (len(idx), 1))
            e = irradiance(scanner, sources, torch.as_tensor(p_cam[idx]), torch.as_tensor(up)).numpy()
            good &= (e > 1e-9).all(1)
            value[idx[good]] = math.pi * y[good] / e[good]
        samples.append(value.astype(np.float32))
    stack = np.stack(samples) if samples else np.full((1, len(cells), 3), np.nan, np.float32)
    seen = np.isfinite(stack).all(-1).any(0)
    albedo = np.full((len(cells), 3), np.nan, np.float32)
    albedo[seen] = np.nanmedian(stack[:, seen], axis=0)
    fill = np.median(albedo[seen], axis=0) if seen.any() else np.zeros(3, np.float32)
    albedo[~seen] = fill
    return SupportAlbedo(z, origin, TUNING.support.cell, albedo.reshape(n, n, 3), fill.astype(np.float32))
