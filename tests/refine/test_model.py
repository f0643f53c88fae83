"""The refinement's forward model: which entries are censored, the frame's turn, the start's
parameters in range, the Cauchy cost."""

import math

import numpy as np
import torch
from refine.test_policy import DEV, _traces

from ntp_engine.physics.brdf import ALPHA_MAX, ALPHA_MIN, RHO_S_MAX
from ntp_engine.physics.frame import rotation_from_vector
from ntp_engine.refine.model import P_LOGA, P_OMEGA, P_RHO_D, P_RHO_S, Start, fold, parameters, robust_cost
from ntp_engine.refine.settings import SensorNoise


def test_fold_turns_the_frame_by_the_shading_frame_rotation():
    gen = torch.Generator().manual_seed(1)
    frame = torch.linalg.qr(torch.randn(5, 3, 3, dtype=torch.float64, generator=gen))[0].transpose(1, 2)
    np.testing.assert_allclose(fold(frame, torch.zeros(5, 3, dtype=torch.float64)).numpy(), frame.numpy())
    omega = torch.tensor([[0.0, 0.0, math.pi / 2]] * 5, dtype=torch.float64)  # a quarter turn about n
    turned = fold(frame, omega)
    np.testing.assert_allclose(turned[:, 2].numpy(), frame[:, 2].numpy(), atol=1e-12)  # n kept
    np.testing.assert_allclose(turned[:, 0].numpy(), frame[:, 1].numpy(), atol=1e-12)  # t -> b
    np.testing.assert_allclose(turned.numpy(), (rotation_from_vector(omega).transpose(1, 2) @ frame).numpy())


def test_a_start_becomes_parameters_in_range_with_no_turn():
    n = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.6, 0.8]])
    t = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    start = Start(
        n, t, torch.tensor([[1e-6, 0.2], [5.0, 0.1]]), torch.tensor([[-1.0, 0.5, 2.0]] * 2), torch.full((2, 3), 99.0)
    )
    frame, p = parameters(start, torch.float64)
    assert p.dtype == torch.float64 and p.shape == (2, 11)
    assert (p[:, P_OMEGA] == 0).all()
    np.testing.assert_allclose(p[:, P_LOGA].exp().numpy(), [[ALPHA_MIN, 0.2], [ALPHA_MAX, 0.1]], rtol=1e-6)
    assert p[:, P_RHO_D].min() == 0 and (p[:, P_RHO_S] == RHO_S_MAX).all()
    np.testing.assert_allclose(frame[:, 2].numpy(), n.double().numpy(), atol=1e-7)


def test_the_cauchy_cost_is_quadratic_near_zero_and_grows_only_logarithmically():
    r = torch.tensor([[[0.01, 0.0, 0.0]], [[100.0, 0.0, 0.0]]], dtype=torch.float64)
    c = robust_cost(r, 3.0)
    assert abs(c[0].item() - 0.5 * 0.01**2) < 1e-9  # half chi-square for small residuals
    assert c[1].item() < 0.5 * 100.0**2 / 100  # far residuals count far less than their square


def test_a_clipped_channel_is_a_lower_bound_alone():
    """The camera clips each channel on its own (``scanner.camera.encode``): an entry whose red code
    is above ``CENSOR_CODE`` says "at least this bright" in red only; its green and blue, in range,
    are measurements (read as lower bounds too, a bright red material's green and blue would say
    nothing where its red clips)."""
    from ntp_engine.refine.model import Trace
    from ntp_engine.refine.settings import CENSOR_CODE

    entries, mask, _ = _traces(8, 23, (0.5, 0.3, 0.2), (0.0, 0.0, 0.0), (0.3, 0.3))
    entries = entries.clone()
    red = torch.rand(mask.shape, generator=torch.Generator().manual_seed(0)) < 0.5
    entries[..., 0] = torch.where(red, (CENSOR_CODE + 10) / 255, 0.5)
    entries[..., 1:3] = 0.4
    tr = Trace(DEV, entries, mask, SensorNoise(), None)
    np.testing.assert_array_equal(tr.censored[..., 0].numpy(), (red & mask).numpy())
    assert not tr.censored[..., 1:].any()


def test_a_starts_rows_are_every_field_of_those_texels():
    fields = [torch.arange(4 * w, dtype=torch.float32).reshape(4, w) for w in (3, 3, 2, 3, 3)]
    sub = Start(*fields).rows(torch.tensor([2, 0]))
    for got, whole in zip(sub, fields, strict=True):
        torch.testing.assert_close(got, whole[[2, 0]])
