import pytest
import torch

from ntp_engine.fit.flags import TexelFlag
from ntp_engine.fit.geometry import GeometryFit
from ntp_engine.fit.highlights import flag_unseen_highlights
from ntp_engine.io.assets import DEVICES_DIR
from ntp_engine.scanner.device_file import load_scanner


def test_texels_whose_highlight_was_never_seen_are_flagged_with_the_fallback_lobe():

    dev = load_scanner(DEVICES_DIR / "point_light.toml")
    light = torch.as_tensor(dev.emitter_positions[0])
    x = torch.tensor([[0.0, 0.0, 0.3]], dtype=torch.float64).expand(2, 3)
    # texel 0: geometric normal = the half vector between light and camera (peak seen);
    # texel 1: tilted 35 deg away, a sharp lobe whose mirror direction misses the only light
    h = torch.nn.functional.normalize(
        torch.nn.functional.normalize(light - x[0], dim=0) + torch.nn.functional.normalize(-x[0], dim=0), dim=0
    )
    away = torch.nn.functional.normalize(h + 0.7 * torch.tensor([1.0, 0, 0], dtype=torch.float64), dim=0)
    n_geo = torch.stack([h, away])[:, None]
    t_geo = torch.nn.functional.normalize(
        torch.linalg.cross(n_geo, torch.tensor([0, 1.0, 0], dtype=torch.float64).expand_as(n_geo), dim=-1), dim=-1
    )
    z = torch.tensor([[0.0, 0, 1], [0.0, 0, 1]])
    geo = GeometryFit(
        z,
        torch.tensor([[1.0, 0, 0], [1.0, 0, 0]]),
        torch.tensor([0.02, 0.02]),
        torch.tensor([0.02, 0.02]),
        torch.ones(2),
        torch.zeros(2, dtype=torch.int64),
        None,
    )
    beta = flag_unseen_highlights(dev, x[:, None], n_geo, t_geo, torch.ones(2, 1, dtype=torch.bool), geo)
    assert float(beta[0]) == pytest.approx(1.0) and float(beta[1]) < 1e-3
    assert geo.flags.tolist() == [0, TexelFlag.NO_HIGHLIGHT]
    assert geo.alpha_x.tolist() == pytest.approx([0.02, 0.3]) and torch.isfinite(geo.normal).all()
