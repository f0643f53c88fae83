"""The support's light (refine.support_light): its sums against a dense integral over the plane, its
albedo read back from an engine scan's photos, and the refinement with it on synthetic traces."""

import math

import numpy as np
import pytest
import torch

from ntp_engine.io.tuned import retuned
from ntp_engine.physics.brdf import fresnel_schlick, ggx
from ntp_engine.physics.frame import frame_from_normal_tangent
from ntp_engine.refine import support_light as sl
from ntp_engine.refine.model import Observations
from ntp_engine.scanner.camera import look_at
from ntp_engine.scanner.device_file import load_scanner

DEV = load_scanner()
ALBEDO = sl.SupportAlbedo(0.0, np.array([-1.0, -1.0]), 2.0, np.full((1, 1, 3), 0.5), np.full(3, 0.5))


def _vertical_texel(cam_pos):
    """A texel on a face looking along +x, 2 cm above the support, seen from ``cam_pos`` (world):
    its view, one entry's camera-space point and frame, and wo (geometric frame)."""
    pos = torch.tensor([0.03, 0.0, 0.02], dtype=torch.float64)
    fw = frame_from_normal_tangent(torch.tensor([[1.0, 0, 0]]), torch.tensor([[0, 0, 1.0]])).double()
    pose = torch.as_tensor(look_at(np.asarray(cam_pos, float), pos.numpy()))
    R, t = pose[:3, :3], pose[:3, 3]
    x_cam = (R @ pos + t)[None, None]
    fc = (fw @ R.T)[:, None]  # rows t^, b^, n^ in camera space (1, 1, 3, 3)
    wo = -(fc @ x_cam[..., None])[..., 0]
    view = sl.SupportView(sl.SupportScene(ALBEDO), pos[None], fw)
    return view, x_cam, fc, wo / wo.norm(dim=-1, keepdim=True), R, t, pos, fw[0]


def _dense(R, t, pos, fw, wo, alphas):
    """Specular (rho_s = 1, per alpha pair of ``alphas``) and diffuse (rho_d = 1) light of the
    support on the texel, by a 1 mm grid over +-0.6 m of the plane."""
    g = torch.linspace(-0.6, 0.6, 1201, dtype=torch.float64)
    X, Y = torch.meshgrid(g, g, indexing="ij")
    P = torch.stack([X.reshape(-1), Y.reshape(-1), torch.zeros(X.numel(), dtype=torch.float64)], -1)
    d = P - pos
    r2 = (d * d).sum(-1)
    w = d / r2.sqrt()[:, None]
    domega = (g[1] - g[0]) ** 2 * (-w[:, 2]).clamp_min(0) / r2
    L = 0.5 / math.pi * sl.irradiance(DEV, sl.Sources.of(DEV), P @ R.T + t, R[:, 2].expand(len(P), 3))
    wl = w @ fw.T  # into the texel's frame
    cos = wl[:, 2].clamp_min(0)
    spec = []
    for ax, ay in alphas:
        f = ggx(wl, wo.expand_as(wl), torch.zeros(1), torch.ones(1), torch.tensor(ax), torch.tensor(ay))[..., 0]
        spec.append(((f * cos * domega)[:, None] * L).sum(0))
    return spec, ((cos * domega / math.pi)[:, None] * L).sum(0)


def test_the_support_sums_converge_to_the_integral_over_the_plane(monkeypatch):
    """The Monte Carlo sums of a face seen from above the support converge to the plane's integral
    and are unbiased over entries: the same entry with 64 lattice shifts averages within 1% of it at
    256 samples (one shift alone within 6%) and within 4% at the shipped counts (one alone within
    40%), for a broad and an anisotropic lobe."""
    view, x_cam, fc, wo, R, t, pos, fw = _vertical_texel([0.25, 0.1, 0.18])
    alphas = [(0.3, 0.3), (0.05, 0.2)]
    spec_ref, diff_ref = _dense(R, t, pos, fw, wo[0, 0], alphas)
    E = 64  # the entry repeated, each copy with its own lattice shift
    g = (torch.arange(8, dtype=torch.float64) + 0.5) / 8
    shifts = torch.stack(torch.meshgrid(g, g, indexing="ij"), -1).reshape(1, E, 2)
    monkeypatch.setattr(sl, "entry_shifts", lambda x: shifts.expand(len(x), E, 2))
    x_e, fc_e, wo_e = x_cam.expand(1, E, 3), fc.expand(1, E, 3, 3), wo.expand(1, E, 3)
    live = torch.ones(1, E, dtype=torch.bool)
    eye = torch.eye(3, dtype=torch.float64)[None]
    for samples, each, mean in ((None, 0.4, 0.04), (256, 0.06, 0.01)):
        if samples:
            retune = retuned(sl.TUNING, "support", specular_samples=samples, diffuse_samples=samples)
            monkeypatch.setattr(sl, "TUNING", retune)
        diff = sl.support_diffuse_basis(view, DEV, sl.Sources.of(DEV), x_e, fc_e, live)[0, :, :, 2] / diff_ref
        assert ((diff - 1).abs() < each).all() and ((diff.mean(0) - 1).abs() < mean).all(), (samples, diff.mean(0))
        for alpha, ref in zip(alphas, spec_ref):
            a = torch.tensor([alpha], dtype=torch.float64)
            em = sl.support_specular_emitters(view, DEV, sl.Sources.of(DEV), x_e, fc_e, live, wo_e, eye, a)
            wi, weight, drive = em.wi[0], em.weight[0], em.drive[0]  # (E, S, ...)
            f = ggx(wi, wo[0, 0].expand_as(wi), torch.zeros(1), torch.ones(1), a[0, 0], a[0, 1])[..., 0]
            spec = ((f * wi[..., 2].clamp_min(0) * weight)[..., None] * drive).sum(1) / ref
            assert torch.isfinite(spec).all()
            assert ((spec - 1).abs() < each).all(), (samples, alpha, spec.min(0), spec.max(0))
            assert ((spec.mean(0) - 1).abs() < mean).all(), (samples, alpha, spec.mean(0))


def test_entry_shifts_are_each_entrys_own():
    """The lattice shift of an entry is a function of its point alone (the same in any chunk), in
    [0, 1), and differs between points half a millimetre apart."""
    x = torch.tensor([[[0.01, -0.02, 0.25], [0.0105, -0.02, 0.25], [0.01, -0.02, 0.25]]], dtype=torch.float64)
    s = sl.entry_shifts(x)
    assert s.shape == (1, 3, 2) and bool(((s >= 0) & (s < 1)).all())
    assert torch.equal(s[0, 0], s[0, 2]) and bool(((s[0, 0] - s[0, 1]).abs() > 1e-3).all())
    assert torch.equal(sl.entry_shifts(x[:, 1:]), s[:, 1:])
    many = sl.entry_shifts(
        torch.rand(1, 4096, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 0.3
    )
    assert (many.mean((0, 1)) - 0.5).abs().max() < 0.03  # spread over the square


def test_the_support_light_reflects_with_the_bounded_fresnel():
    """With the lobe's rho_s, each specular sample's light is scaled by the bounded Fresnel over the
    BRDF's at its w_i.h (so rho_s F <= 1 at grazing); rho_s <= 1 leaves it as it was."""
    view, x_cam, fc, wo, *_ = _vertical_texel([0.25, 0.1, 0.18])
    live = torch.ones(1, 1, dtype=torch.bool)
    eye = torch.eye(3, dtype=torch.float64)[None]
    a = torch.tensor([[0.3, 0.3]], dtype=torch.float64)
    args = (view, DEV, sl.Sources.of(DEV), x_cam, fc, live, wo, eye, a)
    plain = sl.support_specular_emitters(*args)
    rho_s = torch.tensor([[10.0, 2.0, 0.5]], dtype=torch.float64)
    bounded = sl.support_specular_emitters(*args, rho_s)
    wi = plain.wi[0, 0]
    h = torch.nn.functional.normalize(wi + wo[0, 0], dim=-1)
    c = (wi * h).sum(-1, keepdim=True)
    lit = plain.drive[0, 0].sum(-1) > 0
    assert lit.sum() >= 4 and float(c[lit].min()) < 0.8  # some samples far from w_i.h = 1
    want = fresnel_schlick(c, 0.04, 1 / rho_s[0].clamp_min(1)) / fresnel_schlick(c)
    torch.testing.assert_close(bounded.drive[0, 0], plain.drive[0, 0] * want, rtol=1e-12, atol=0)
    assert bool((bounded.drive[0, 0, lit, 0] < plain.drive[0, 0, lit, 0]).all())
    torch.testing.assert_close(bounded.drive[0, 0, :, 2], plain.drive[0, 0, :, 2], rtol=1e-12, atol=0)
    torch.testing.assert_close(bounded.wi, plain.wi)


def test_directions_that_miss_the_support_carry_no_light():
    """A face looking up sees no support: nothing from its diffuse samples; nor does a face with a
    wall (the mesh) between it and the support."""
    view, x_cam, fc, wo, *_ = _vertical_texel([0.25, 0.1, 0.18])
    up = frame_from_normal_tangent(torch.tensor([[0, 0, 1.0]]), torch.tensor([[1.0, 0, 0]])).double()
    flat = sl.SupportView(view.scene, view.position, up)
    live = torch.ones(1, 1, dtype=torch.bool)
    assert (sl.support_diffuse_basis(flat, DEV, sl.Sources.of(DEV), x_cam, fc, live) == 0).all()
    from ntp_engine.io.raycast import RayCaster

    # a wall in front of the face up to just below the texel: it hides the whole support
    a, b, c, d = [0.035, -2, -0.01], [0.035, 2, -0.01], [0.035, 2, 0.0199], [0.035, -2, 0.0199]
    wall = np.array([[a, b, c], [a, c, d]])
    walled = sl.SupportView(sl.SupportScene(ALBEDO, RayCaster([wall])), view.position, view.frame_world)
    open_ = sl.support_diffuse_basis(view, DEV, sl.Sources.of(DEV), x_cam, fc, live)
    hidden = sl.support_diffuse_basis(walled, DEV, sl.Sources.of(DEV), x_cam, fc, live)
    assert open_[..., 2].min() > 0 and (hidden == 0).all()


def test_the_refinement_with_the_support_recovers_a_glossy_face_it_lights():
    """Synthetic traces of a broad glossy lobe on a face 2 cm above a lit support (its light, summed
    with 512 samples, is ~16% of the median pixel): with the support's light in the model the
    refinement recovers the normal, alpha and rho_s from a perturbed start; without, Eq. 1 alone
    tips the normal by degrees and misreads the lobe."""
    from refine.test_policy import _normal_err, _perturbed, _traces

    from ntp_engine.refine.model import Start
    from ntp_engine.refine.pixel_bases import pack_emitters, specular_basis
    from ntp_engine.refine.policy import refine

    n = 32
    entries, mask, p = _traces(n, 1, (0.05, 0.05, 0.05), (4.0, 4.0, 4.0), (0.2, 0.2), noise=0.0)
    fw = frame_from_normal_tangent(torch.tensor([[1.0, 0, 0]]), torch.tensor([[0, 0, 1.0]])).double().expand(n, 3, 3)
    pos = torch.tensor([[0.0, 0.0, 0.02]], dtype=torch.float64).expand(n, 3)
    albedo = sl.SupportAlbedo(0.0, np.array([-1.0, -1.0]), 2.0, np.full((1, 1, 3), 0.6), np.full(3, 0.6))
    view = sl.SupportView(sl.SupportScene(albedo), pos, fw)
    x = entries[..., 3:6].double()
    fc = frame_from_normal_tangent(entries[..., 6:9].double(), entries[..., 9:12].double())
    wo = -(fc @ x[..., None])[..., 0]
    wo = wo / wo.norm(dim=-1, keepdim=True)
    true_frame = frame_from_normal_tangent(p["n_local"].double(), p["t_local"].double())
    alpha = torch.stack([p["alpha_x"], p["alpha_y"]], 1).double()
    src = sl.Sources.of(DEV)
    with pytest.MonkeyPatch.context() as patch:  # the truth: many samples, the bounded Fresnel
        patch.setattr(sl, "TUNING", retuned(sl.TUNING, "support", specular_samples=512, diffuse_samples=512))
        em = sl.support_specular_emitters(view, DEV, src, x, fc, mask, wo, true_frame, alpha, p["rho_s"].double())
        spec = specular_basis(true_frame, pack_emitters(em.wi.transpose(-1, -2), em.weight, em.drive), wo, alpha)
        diff = (sl.support_diffuse_basis(view, DEV, src, x, fc, mask) * true_frame[:, None, None, 2]).sum(-1)
    extra = p["rho_d"][:, None].double() * diff + p["rho_s"][:, None].double() * spec
    y = entries[..., :3].double() + extra
    assert (extra.mean(-1) / y.mean(-1))[mask].median() > 0.1
    entries[..., :3] = (torch.round((y * 255).clamp(0, 255)) / 255).float()
    start, lobe = Start(*_perturbed(p, 2)), torch.ones(n, dtype=torch.bool)
    errors = {}
    for name, support in (("with", view), ("without", None)):
        r = refine(Observations(DEV, entries, mask, support=support), start, lobe)
        assert torch.isfinite(r.frame).all() and torch.isfinite(r.rho_s).all()
        errors[name] = (
            _normal_err(r, p).median(),
            (r.log_alpha - alpha.log().float()).abs().median(),
            (r.rho_s.mean(1) / 4.0).log().abs().median(),
        )
    # measured: with 1.04 deg, |log alpha| 0.05, |log rho_s| 0.05; without 3.9 deg, 0.69, 0.92 (the
    # BRDF's unbounded Fresnel in the truth and the model, until 2026-11-29: 1.05 / 0.08 / 0.07, 5.1)
    assert errors["with"][0] < 2.0 and errors["with"][1] < 0.2 and errors["with"][2] < 0.15, errors
    assert errors["without"][0] > 3.0 and errors["without"][2] > 0.4, errors


def test_the_light_bounced_onto_an_entry_weighs_it_down():
    """The model's bounced light is uncertain (``RefineTuning.model.bounce_noise``): each entry's sigma gains that
    factor times its pixel times its share of bounced light (of the diffuse light at the geometric
    normal), in quadrature, whatever the answer judged; without a support the sensor's alone."""
    from refine.test_policy import _perturbed, _traces

    from ntp_engine.refine.model import Start, predicted_light
    from ntp_engine.refine.settings import TUNING

    n = 8
    entries, mask, p = _traces(n, 3, (0.3, 0.3, 0.3), (0.5, 0.5, 0.5), (0.2, 0.2), noise=0.0)
    fw = frame_from_normal_tangent(torch.tensor([[1.0, 0, 0]]), torch.tensor([[0, 0, 1.0]])).double().expand(n, 3, 3)
    view = sl.SupportView(
        sl.SupportScene(ALBEDO), torch.tensor([[0.0, 0.0, 0.02]], dtype=torch.float64).expand(n, 3), fw
    )
    up, along = torch.zeros(n, 3), torch.zeros(n, 3)
    up[:, 2], along[:, 0] = 1.0, 1.0
    matte = Start(up, along, torch.full((n, 2), 0.2), torch.ones(n, 3), torch.zeros(n, 3))
    d_with, _, inv_with = predicted_light(Observations(DEV, entries, mask, support=view), matte)
    d_without, _, inv_without = predicted_light(Observations(DEV, entries, mask), matte)
    live = inv_without > 0
    share = ((d_with - d_without) / d_with).double()
    assert (share[live] > 0.1).float().mean() > 0.2  # the case is real: a fifth of the entries 10% bounced
    sigma = 1.0 / inv_without.double()
    expected = torch.rsqrt(sigma**2 + (TUNING.model.bounce_noise * share * entries[..., :3].double()) ** 2)
    assert torch.allclose(inv_with[live].double(), expected[live], rtol=1e-4)
    bounced = live & (share > 0.1)
    assert inv_with[bounced].mean() < 0.8 * inv_without[bounced].mean()  # they weigh less
    # another answer (a lobe, the normal tipped) is judged on the same scale
    glossy = Start(*_perturbed(p, 5, tilt_deg=6.0))
    assert torch.equal(predicted_light(Observations(DEV, entries, mask, support=view), glossy)[2], inv_with)


def test_the_support_albedo_is_read_back_from_an_engine_scan(scan24):
    """The support's albedo map from the photos of a virtual scan (the engine shades its marker
    backdrop lit by the scanner, unshadowed) against the backdrop's true albedo at the cells."""
    from ntp_engine.io.mesh import load_mesh
    from ntp_engine.io.raycast import RayCaster
    from ntp_engine.scanner import camera
    from ntp_engine.scanner.scan_folder import load_poses, load_scan, read_photo
    from ntp_engine.sim.renderer import marker_albedo

    scan = load_scan(scan24)
    poses = load_poses(scan24 / "ground_truth" / "poses.json")
    names = sorted(poses)
    mesh = load_mesh(scan.mesh_path)

    def photos():
        for n in names:
            codes = read_photo(scan.photos_dir / n, scan.scanner)
            yield camera.decode(scan.scanner, torch.as_tensor(codes, dtype=torch.float64)).numpy(), codes

    est = sl.estimate_support_albedo(
        photos(), [poses[n] for n in names], scan.scanner, mesh.vertices, RayCaster([mesh.triangles])
    )
    H, W, _ = est.albedo.shape
    assert est.z == pytest.approx(float(mesh.vertices[:, 2].min())) and H == W > 50
    jj, ii = np.meshgrid(np.arange(W), np.arange(H))
    xy = np.stack([est.origin[0] + (jj + 0.5) * est.cell, est.origin[1] + (ii + 0.5) * est.cell], -1).reshape(-1, 2)
    truth = marker_albedo(xy)
    ratio = est.albedo.reshape(-1, 3)[:, 0] / truth
    assert np.isfinite(est.albedo).all() and abs(np.median(ratio) - 1) < 0.03, np.median(ratio)
    assert np.percentile(np.abs(ratio - 1), 75) < 0.1
    looked_up = est.at(torch.as_tensor(xy[:5]))
    assert torch.allclose(looked_up, torch.as_tensor(est.albedo.reshape(-1, 3)[:5], dtype=torch.float64))
    assert torch.allclose(est.at(torch.tensor([[5.0, 5.0]], dtype=torch.float64)), torch.as_tensor(est.fill).double())


def _walled_texel(facing=1.0):
    """The vertical texel of ``_vertical_texel`` seen from the -y side, beside a wall of the object
    in the plane y = 2 cm (x 3-20 cm, z 0-20 cm) whose face looks toward -y (``facing`` -1: its
    normal turned away), albedo 0.7: the view with the wall's light and one without it."""
    view, x_cam, fc, wo, R, t, pos, fw = _vertical_texel([0.25, -0.1, 0.18])
    from ntp_engine.io.raycast import RayCaster

    a, b, c, d = [0.03, 0.02, 0.0], [0.2, 0.02, 0.0], [0.2, 0.02, 0.2], [0.03, 0.02, 0.2]
    wall = np.array([[a, b, c], [a, c, d]])
    normal = np.tile([0.0, -facing, 0.0], (2, 1))
    lit = sl.SupportScene(ALBEDO, RayCaster([wall]), normal, np.full((2, 3), 0.7))
    dark = sl.SupportScene(ALBEDO, lit.caster, normal, np.zeros((2, 3)))
    views = [sl.SupportView(s, view.position, view.frame_world) for s in (lit, dark)]
    return views, x_cam, fc, R, t, pos, fw


def test_the_objects_own_light_converges_to_the_integral_over_its_lit_face(monkeypatch):
    """A face beside a lit wall of the object receives the wall's diffuse light (albedo / pi times
    the scanner's irradiance there): the diffuse basis' share from the wall (with its albedo minus
    without) converges to a dense integral over the wall (measured: 0.84 of it at the shipped 32
    samples, 0.972 at 256, 0.9999 at 2048), two entries' sums as each one's alone; a wall whose
    face looks away gives none."""
    views, x_cam, fc, R, t, pos, fw = _walled_texel()
    g = torch.linspace(0.0, 0.2, 401, dtype=torch.float64)
    X, Z = torch.meshgrid(g[g >= 0.03], g, indexing="ij")
    P = torch.stack([X.reshape(-1), torch.full((X.numel(),), 0.02, dtype=torch.float64), Z.reshape(-1)], -1)
    d = P - pos
    r2 = (d * d).sum(-1)
    w = d / r2.sqrt()[:, None]
    domega = (g[1] - g[0]) ** 2 * w[:, 1].clamp_min(0) / r2  # the wall's normal is -y
    wall_normal_cam = torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64) @ R.T
    L = 0.7 / math.pi * sl.irradiance(DEV, sl.Sources.of(DEV), P @ R.T + t, wall_normal_cam.expand(len(P), 3))
    cos = (w @ fw.T)[:, 2].clamp_min(0)
    ref = ((cos * domega / math.pi)[:, None] * L).sum(0)
    live = torch.ones(1, 1, dtype=torch.bool)
    for samples, tol in ((None, 0.25), (256, 0.04), (2048, 0.01)):
        if samples:
            monkeypatch.setattr(sl, "TUNING", retuned(sl.TUNING, "support", diffuse_samples=samples))
        lit, dark = (sl.support_diffuse_basis(v, DEV, sl.Sources.of(DEV), x_cam, fc, live)[0, 0, :, 2] for v in views)
        assert ((lit - dark) / ref - 1).abs().max() < tol, (samples, (lit - dark) / ref)
    # two entries summed together as each alone
    _, x2, fc2, *_ = _vertical_texel([0.2, -0.2, 0.1])
    both = sl.support_diffuse_basis(
        views[0],
        DEV,
        sl.Sources.of(DEV),
        torch.cat([x_cam, x2], 1),
        torch.cat([fc, fc2], 1),
        torch.ones(1, 2, dtype=torch.bool),
    )
    for j, (x, f) in enumerate(((x_cam, fc), (x2, fc2))):
        alone = sl.support_diffuse_basis(views[0], DEV, sl.Sources.of(DEV), x, f, live)[0, 0]
        torch.testing.assert_close(both[0, j], alone, rtol=1e-12, atol=0.0)
    away, x_cam, fc, *_ = _walled_texel(facing=-1.0)
    lit, dark = (sl.support_diffuse_basis(v, DEV, sl.Sources.of(DEV), x_cam, fc, live) for v in away)
    assert torch.equal(lit, dark)


def _box_triangles(lo, hi):
    """The 12 outward-wound triangles ``(12, 3, 3)`` of the box ``lo``-``hi`` (corners, m)."""
    c = np.array([[(hi if (k >> a) & 1 else lo)[a] for a in range(3)] for k in range(8)], float)
    quads = [(0, 2, 6, 4), (1, 5, 7, 3), (0, 4, 5, 1), (2, 3, 7, 6), (0, 1, 3, 2), (4, 6, 7, 5)]
    tri = [[c[q[0]], c[q[i]], c[q[i + 1]]] for q in quads for i in (1, 2)]
    return np.array(tri)


def test_a_texel_is_exposed_only_with_the_whole_mesh_behind_its_plane():
    """``exposed``: a box's face centres and an edge texel whose normal leans over the edge are (the
    other corners lie behind their planes, one within ray_offset / 2 counts as on it); a texel on
    the floor beside a wall is not, nor one with a corner 0.6 ray_offset above its plane."""
    box = _box_triangles(np.array([-0.03, -0.03, 0.0]), np.array([0.03, 0.03, 0.04])).reshape(-1, 3)
    lean = np.array([1.0, 0.0, 1.0]) / math.sqrt(2)
    pos = np.array([[0.03, 0.0, 0.02], [0.0, 0.0, 0.04], [0.03, 0.0, 0.04]])
    nrm = np.array([[1.0, 0, 0], [0, 0, 1.0], lean])
    assert sl.exposed(box, pos, nrm).tolist() == [True, True, True]
    floor_and_wall = np.array([[-0.1, -0.1, 0.0], [0.1, -0.1, 0.0], [0.1, 0.1, 0.0], [0.05, 0.0, 0.03]])
    assert sl.exposed(floor_and_wall, np.zeros((1, 3)), np.array([[0, 0, 1.0]])).tolist() == [False]
    for height, want in ((0.4, True), (0.6, False)):
        corner = np.array([[0.02, 0.0, height * sl.TUNING.support.ray_offset], [-0.02, 0.0, -0.01]])
        assert sl.exposed(corner, np.zeros((1, 3)), np.array([[0, 0, 1.0]])).tolist() == [want]


def test_an_exposed_texels_rays_above_its_plane_are_not_cast(monkeypatch):
    """A texel on a side of a box standing on the support, its mesh the caster: its support light
    is the same with its rays above the plane left uncast (all its diffuse samples: no ray at
    all) as with every ray cast; beside a wall it is not exposed, and the wall still hides the support."""
    from ntp_engine.io.raycast import RayCaster

    view, x_cam, fc, *_ = _vertical_texel([0.25, 0.1, 0.18])
    tri = _box_triangles(np.array([-0.03, -0.03, 0.0]), np.array([0.03, 0.03, 0.04]))
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    scene = sl.SupportScene(ALBEDO, RayCaster([tri]), normal, np.full((12, 3), 0.5))
    flag = torch.as_tensor(sl.exposed(tri.reshape(-1, 3), view.position.numpy(), view.frame_world[:, 2].numpy()))
    assert flag.tolist() == [True]
    cast = []
    intersect = RayCaster.intersect
    monkeypatch.setattr(RayCaster, "intersect", lambda self, o, d: cast.append(len(o)) or intersect(self, o, d))
    live = torch.ones(1, 1, dtype=torch.bool)
    every = sl.support_diffuse_basis(
        sl.SupportView(scene, view.position, view.frame_world), DEV, sl.Sources.of(DEV), x_cam, fc, live
    )
    assert sum(cast) == sl.TUNING.support.diffuse_samples
    cast.clear()
    view_exposed = sl.SupportView(scene, view.position, view.frame_world, flag)
    skipped = sl.support_diffuse_basis(view_exposed, DEV, sl.Sources.of(DEV), x_cam, fc, live)
    assert sum(cast) == 0 and every[..., 2].min() > 0
    torch.testing.assert_close(skipped, every, rtol=0, atol=0)
    # a wall in front of the face hides the support: the texel is not exposed, its rays are cast
    a, b, c, d = [0.035, -2, -0.01], [0.035, 2, -0.01], [0.035, 2, 0.0199], [0.035, -2, 0.0199]
    wall = np.array([[a, b, c], [a, c, d]])
    walled = np.concatenate([tri, wall])
    flag = torch.as_tensor(sl.exposed(walled.reshape(-1, 3), view.position.numpy(), view.frame_world[:, 2].numpy()))
    assert flag.tolist() == [False]
    hidden = sl.SupportView(sl.SupportScene(ALBEDO, RayCaster([walled])), view.position, view.frame_world, flag)
    assert (sl.support_diffuse_basis(hidden, DEV, sl.Sources.of(DEV), x_cam, fc, live) == 0).all()


def test_face_albedo_is_the_mean_of_each_triangles_known_texels():
    """Per triangle the mean of its known texels' albedos; a triangle with none, their median."""
    rho_d = np.array([[0.2, 0.2, 0.2], [0.4, 0.4, 0.4], [0.9, 0.9, 0.9], [0.5, 0.5, 0.5]])
    face = np.array([0, 0, 1, 2])
    known = np.array([True, True, True, False])
    got = sl.face_albedo(4, face, rho_d, known)
    np.testing.assert_allclose(got[:, 0], [0.3, 0.9, 0.4, 0.4])
    assert (sl.face_albedo(2, face[:0], rho_d[:0], known[:0]) == 0).all()
