"""Cylinders grouped into stems (core/mapping/stem_groups.py)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from forestmap_assets.core.mapping.stem_groups import group_stems


def _cyl(rows):
    """Cylinders from (x0, y0, z0, x1, y1, z1, radius)."""
    return pd.DataFrame(rows, columns=["x0", "y0", "z0", "x1", "y1", "z1", "radius_m"])


def test_two_stems_joined_across_a_gap_are_kept_apart():
    """Stem A (vertical at x = 0) and stem B (1.1 m away, leaning 0.6 deg towards A): a short
    cylinder tilted off A's top lines up, 9.6 m higher, with a short one on B, and that one
    with B's trunk, so the links chain A to B. A and B stand side by side at their bases: two
    stems, two groups. Without that rule (no pair counts as side by side) they are one."""
    b = lambda z: 1.1 - 0.01 * (z + 1)  # noqa: E731  B's axis
    cyl = _cyl([
        (0.0, 0, -1.0, 0.0, 0, 2.2, 0.12),  # A's trunk
        (0.0, 0, 2.4, 0.1124, 0, 3.0, 0.10),  # tilted off A's top
        (b(12.6), 0, 12.6, b(13.2), 0, 13.2, 0.10),  # high on B
        (b(-1.0), 0, -1.0, b(3.0), 0, 3.0, 0.12),  # B's trunk
    ])
    labels = group_stems(cyl)
    assert labels[0] == labels[1] and labels[2] == labels[3]
    assert labels[0] != labels[3]
    joined = group_stems(cyl, min_overlap_m=np.inf)
    assert len(set(joined)) == 1


def test_a_forked_stem_stays_one_tree():
    """Two leaders side by side above a fork 4.2 m up the stem are one stem (the rule keeps
    stems apart only within 2 m of the lowest cylinder around them)."""
    cyl = _cyl([
        (0.0, 0, -1.0, 0.0, 0, 3.0, 0.12),
        (0.0, 0, 3.2, -0.4, 0, 7.0, 0.08),
        (0.0, 0, 3.2, 0.4, 0, 7.0, 0.08),
    ])
    assert len(set(group_stems(cyl))) == 1
    assert len(set(group_stems(cyl, base_height_m=10.0))) == 2


def test_a_fork_limb_reaching_a_neighbour_2_5_m_away_keeps_the_two_trees():
    """Own realistic 174: stem A forks 4.8 m up, its limb leaning towards stem B standing 2.5 m
    away; the limb's axis runs into a cylinder high on B, so the links chain A's group to B's.
    The two trunks stand side by side near the ground, further apart than the 2 m the rule once
    looked (both read as one 29 cm tree between them): the trunks stay in two groups. Looking
    only 2 m around, all is one."""
    limb = lambda z: 0.12 + (2.5 - 0.12) / (9.2 - 4.8) * (z - 4.8)  # noqa: E731  x at height z
    cyl = _cyl([
        (0.0, 0, -1.0, 0.0, 0, 4.6, 0.14),  # A's trunk
        (0.12, 0, 4.8, limb(6.0), 0, 6.0, 0.08),  # the limb, up towards B
        (limb(6.2), 0, 6.2, limb(7.6), 0, 7.6, 0.07),
        (limb(7.8), 0, 7.8, limb(9.0), 0, 9.0, 0.07),
        (2.5, 0, 9.4, 2.5, 0, 10.4, 0.10),  # high on B, in line with the limb
        (2.5, 0, -1.0, 2.5, 0, 8.0, 0.14),  # B's trunk
    ])
    labels = group_stems(cyl)
    assert labels[0] == labels[1] == labels[2] == labels[3]
    assert labels[0] != labels[5]
    assert len(set(group_stems(cyl, apart_reach_m=2.0))) == 1
