"""Which entries Eq. 1 as the network learnt it describes: steep enough views (``grazing``), emitters
the support hides in a photo (``SupportShadow``) and groups the mesh hides (``shadowed``)."""

import numpy as np
import torch

from ntp_engine.physics.emitter_blocks import shadow_groups
from ntp_engine.physics.shadows import MAX_SHADOWED_DRIVE, MIN_COS_VIEW, SupportShadow, grazing, shadowed
from ntp_engine.scanner.camera import look_at
from ntp_engine.scanner.device_file import load_scanner


def test_an_entry_is_grazing_at_and_below_the_minimum_view_cosine():
    cos = torch.tensor([MIN_COS_VIEW - 0.01, MIN_COS_VIEW + 0.01, 1.0])
    entries = torch.zeros(3, 12)
    entries[:, 3:6] = torch.tensor([0.0, 0.0, 0.3])  # the point, straight ahead of the camera
    sin = (1 - cos**2).sqrt()
    entries[:, 6:9] = torch.stack([sin, torch.zeros(3), -cos], 1)  # normals tilted away from the camera
    assert grazing(entries).tolist() == [True, False, False]


def test_a_photo_from_above_is_not_shadowed_by_the_support_and_one_from_below_it_is():
    dev = load_scanner()
    above = look_at(np.array([0.02, 0.01, 0.25]), np.zeros(3))
    below = look_at(np.array([0.02, 0.01, -0.25]), np.zeros(3))
    support = SupportShadow(dev, 0.0)
    assert not support(above) and support(below)
    groups = shadow_groups(dev)
    assert support.mask(above, groups) == 0
    hidden = groups.hidden(torch.tensor([support.mask(below, groups)]))[0].numpy()
    assert hidden.all()  # every group lies under the plane: the object hides them all


def test_an_entry_is_shadowed_when_its_hidden_groups_carry_more_than_the_allowed_drive():
    groups = shadow_groups(load_scanner())
    order = np.argsort(groups.drive)
    masks = torch.tensor([0, 1 << int(order[-1])], dtype=torch.int64)  # none, the brightest group
    got = shadowed(groups, masks).tolist()
    assert got == [False, bool(groups.drive[order[-1]] > MAX_SHADOWED_DRIVE)]
    assert (groups.share(masks) >= 0).all()
