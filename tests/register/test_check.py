"""The registration check's choices: which photos judge it, which rival azimuths are refined."""

import numpy as np

from ntp_engine.register.check import rival_turns, spread


def test_spread_keeps_the_ends_and_at_most_count():
    names = [f"{i:04d}.png" for i in range(100)]
    picked = spread(list(reversed(names)), 5)
    assert picked == ["0000.png", "0025.png", "0050.png", "0074.png", "0099.png"]  # rounded linspace
    assert spread(names[:3], 5) == names[:3]


def test_rival_turns_are_the_lowest_distinct_minima_away_from_zero():
    turns = np.arange(-180.0, 180.0, 3.0)
    # minima at 0 (the alignment itself), 90 (best rival), 99 (same basin region), -120 and 150
    costs = 2.0 - sum(
        h * np.exp(-0.5 * ((turns - c) / 4.0) ** 2)
        for c, h in [(0, 1.0), (90, 0.8), (99, 0.7), (-120, 0.5), (150, 0.3)]
    )
    rivals = rival_turns(turns, costs, count=3)
    assert rivals == [90.0, -120.0, 150.0]  # 99 is within ambiguous_deg of 90; 0 is not a rival
    assert rival_turns(turns, np.full(len(turns), np.inf)) == []
