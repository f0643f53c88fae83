"""One bit per texel flag, defined once; the bits combine and clear in numpy and torch arrays as ints."""

import numpy as np
import torch

from ntp_engine.fit.flags import TexelFlag
from ntp_engine.refine.inputs import REFINE_FLAGS


def test_each_flag_is_its_own_bit():
    values = [int(f) for f in TexelFlag]
    assert all(v > 0 and v & (v - 1) == 0 for v in values)  # powers of two
    assert len(set(values)) == len(values)
    assert sum(values) < 2**31  # they fit the fit's int32 arrays


def test_the_refinements_bits_clear_without_touching_the_fits():
    fit_bits = TexelFlag.NO_LOBE | TexelFlag.NO_HIGHLIGHT
    flags = np.array([fit_bits | TexelFlag.MARGINAL, TexelFlag.FROM_MATERIAL, 0], np.int32)
    kept = flags & ~int(REFINE_FLAGS)
    assert kept.tolist() == [int(fit_bits), 0, 0]
    t = torch.tensor(flags.astype(np.int64))
    assert ((t & TexelFlag.MARGINAL) != 0).tolist() == [True, False, False]
