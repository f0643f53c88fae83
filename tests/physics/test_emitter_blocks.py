"""Emitter blocks: a partition of the samples into compact blocks whose coarse emitters reproduce a
broad lobe's sum (and not a sharp one's: that is why the brightest blocks are summed sample by sample)."""

import numpy as np
import torch

from ntp_engine.physics.emitter_blocks import EXACT_UP_TO, emitter_blocks
from ntp_engine.physics.measurement import emitter_terms
from ntp_engine.scanner.device_file import load_scanner, shipped_device


def test_led_grid_blocks_are_4x4_squares_partitioning_the_leds():
    dev = load_scanner()
    b = emitter_blocks(dev)
    assert b is not None and b.members.shape == (32, 16) and b.count == 32
    assert sorted(b.members.flatten().tolist()) == list(range(512))  # each LED once, no padding
    pos = dev.emitter_positions[b.members.numpy()]  # (32, 16, 3)
    span = np.linalg.norm(pos[:, :, None] - pos[:, None], axis=-1).max((1, 2))
    np.testing.assert_allclose(span, 0.03 * np.sqrt(2), atol=1e-9)  # 4 x 4 LEDs at 1 cm pitch
    np.testing.assert_allclose(b.coarse_drive.sum(0).numpy(), dev.effective_pattern().sum(0), rtol=1e-12)


def test_small_devices_are_summed_exactly_and_area_lights_blocked():
    assert emitter_blocks(shipped_device("point_light.toml")) is None
    area = shipped_device("area_light.toml")
    b = emitter_blocks(area)
    assert b is not None and b.members.max() <= 32 * 16 and 32 * 16 > EXACT_UP_TO
    real = b.members[b.members < 32 * 16]
    assert len(torch.unique(real)) == len(real) == 32 * 16


def _specular_pixel(dev, blocks, x, n, t, alpha, coarse: bool) -> torch.Tensor:
    a = torch.full(x.shape[:-1], alpha, dtype=x.dtype)
    if coarse:
        _, s = emitter_terms(blocks.coarse, x, n, t, a, a)
        return s @ blocks.coarse_drive.to(x.dtype)
    _, s = emitter_terms(dev, x, n, t, a, a)
    return s @ torch.as_tensor(dev.effective_pattern(), dtype=x.dtype)


def test_coarse_emitters_match_a_broad_lobe_not_a_sharp_one():
    dev = load_scanner()
    blocks = emitter_blocks(dev)
    g = torch.Generator().manual_seed(0)
    x = torch.as_tensor(dev.valid_center) + 0.02 * torch.randn(64, 3, generator=g, dtype=torch.float64)
    n = -x / x.norm(dim=1, keepdim=True) + 0.2 * torch.randn(64, 3, generator=g, dtype=torch.float64)
    n = n / n.norm(dim=1, keepdim=True)
    t = torch.linalg.cross(n, torch.randn(64, 3, generator=g, dtype=torch.float64), dim=-1)
    for alpha, lo, hi in ((0.3, 0.0, 0.03), (0.01, 0.3, np.inf)):
        exact = _specular_pixel(dev, blocks, x, n, t, alpha, False)
        coarse = _specular_pixel(dev, blocks, x, n, t, alpha, True)
        rel = float((coarse - exact).abs().sum() / exact.abs().sum())
        assert lo <= rel < hi, (alpha, rel)


def test_shadow_groups_are_halves_of_the_blocks_and_weigh_what_they_hide():
    """64 groups on the LED grid: each block's two 4 x 2 halves (1 x 3 cm), partitioning the LEDs;
    drive shares summing to 1; a block's visibility is the share of its drive its visible halves
    carry. The point light (summed exactly) has one group per sample and no blocks."""
    from ntp_engine.physics.emitter_blocks import SHADOW_BITS, shadow_groups

    dev = load_scanner()
    g = shadow_groups(dev)
    b = emitter_blocks(dev)
    assert b is not None and g.block is not None and g.fits and len(g.points) == 64 == SHADOW_BITS
    assert torch.equal(torch.bincount(g.group), torch.full((64,), 8))  # 8 LEDs a group
    assert torch.equal(g.block[g.group][b.members], torch.arange(32)[:, None].expand(32, 16))  # within its block
    pos = dev.emitter_positions
    for k in range(64):
        p = pos[g.group.numpy() == k]
        span = np.linalg.norm(p[:, None] - p[None], axis=-1).max()
        np.testing.assert_allclose(span, np.hypot(0.01, 0.03), atol=1e-9)  # a 2 x 4 LED strip at 1 cm pitch
    np.testing.assert_allclose(g.drive.sum(), 1.0)
    one_half = torch.tensor(1 << 6)  # group 6 hidden
    vis = g.block_visibility(one_half, torch.float64)
    c = int(g.block[6])
    block_share = g.drive[(g.block == c).numpy()].sum()
    np.testing.assert_allclose(vis[c].item(), 1 - g.drive[6] / block_share)
    assert (vis[torch.arange(32) != c] == 1).all()
    np.testing.assert_allclose(g.share(one_half).item(), g.drive[6])
    point = shadow_groups(shipped_device("point_light.toml"))
    assert point.block is None and len(point.points) == len(point.group)


def test_the_share_a_mask_hides_is_its_groups_drive_summed():
    """``share`` reads a mask a byte at a time: it equals the drive of the groups whose bits are set,
    summed, for random masks, the sign bit (group 63) set, none and all."""
    from ntp_engine.physics.emitter_blocks import shadow_groups

    g = shadow_groups(load_scanner())
    gen = torch.Generator().manual_seed(0)
    masks = torch.randint(-(2**63), 2**63 - 1, (4000,), generator=gen, dtype=torch.int64)
    masks = torch.cat([masks, torch.tensor([0, -1, -(2**63), 1 << 6])])
    bits = (masks[:, None] >> torch.arange(64)) & 1 == 1
    reference = (bits.double() * torch.from_numpy(g.drive)).sum(-1)
    np.testing.assert_allclose(g.share(masks).numpy(), reference.numpy(), rtol=0, atol=1e-15)
    assert g.share(torch.tensor(0)).item() == 0.0 and abs(g.share(torch.tensor(-1)).item() - 1.0) < 1e-15
    assert g.share(masks.reshape(-1, 2)).shape == (masks.numel() // 2, 2)  # one share a mask
