import numpy as np
import torch

from ntp_engine.io.colour import srgb_decode, srgb_encode


def test_srgb_round_trip_and_reference_values():
    x = np.linspace(0, 1, 1001)
    np.testing.assert_allclose(srgb_decode(srgb_encode(x)), x, atol=1e-12)
    # IEC 61966-2-1: 18% grey encodes to 0.4614, the linear toe below 0.0031308
    np.testing.assert_allclose(srgb_encode(np.array([0.0, 0.001, 0.18, 1.0])), [0, 0.01292, 0.46135, 1], atol=1e-4)
    t = torch.linspace(0, 1, 101, dtype=torch.float64, requires_grad=True)
    y = srgb_encode(t)
    np.testing.assert_allclose(y.detach().numpy(), srgb_encode(t.detach().numpy()), atol=1e-12)
    y.sum().backward()
    assert torch.isfinite(t.grad).all()  # differentiable at 0 (the toe)
