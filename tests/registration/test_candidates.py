"""Candidate pairs and their search boxes (DESIGN.md 2, spec 6.4)."""

from __future__ import annotations

import numpy as np

from forestmap_assets.core.registration.candidates import CANDIDATE_COLUMNS, candidate_pairs


def test_explicit_pairs_centre_box_on_prior():
    df = candidate_pairs(["T", "S"], pairs=[("S", "T", (3.0, -1.0, 1.0, -30.0))],
                         search=(5.0, 1.25, 60.0))
    assert list(df.columns) == list(CANDIDATE_COLUMNS)
    row = df.iloc[0]
    assert (row.scan, row.reference, row.source) == ("S", "T", "pairs")
    assert (row.cx, row.cy, row.cz, row.cheading_deg) == (3.0, -1.0, 1.0, -30.0)
    assert (row.hx, row.hy, row.hz, row.hheading_deg) == (5.0, 5.0, 1.25, 60.0)


def test_a_priori_pairs_grow_linearly_and_use_relative_pose():
    n = 60
    ids = [f"s{i}" for i in range(n)]
    poses = {s: (8.0 * i, 0.5 * i, 0.1 * i, 10.0 * i) for i, s in enumerate(ids)}
    df = candidate_pairs(ids, a_priori=poses, reach={s: 10.0 for s in ids}, k_nearest=3)
    assert len(df) <= 3 * n
    assert (df.source == "a_priori").all()
    got = set(zip(df.scan, df.reference, strict=True))
    for i in range(n - 1):  # neighbours 8 m apart always overlap (reach 10 + 10)
        assert (ids[i + 1], ids[i]) in got
    assert all(abs(int(s[1:]) - int(r[1:])) <= 2 for s, r in got)  # 16 m < 20 m, 24 m > 20 m
    row = df[(df.scan == "s1") & (df.reference == "s0")].iloc[0]
    h = np.radians(0.0)
    assert np.isclose(row.cx, 8.0 * np.cos(h)) and np.isclose(row.cy, 0.5)
    assert np.isclose(row.cz, 0.1) and np.isclose(row.cheading_deg, 10.0)
    far = candidate_pairs(["a", "b"], a_priori={"a": (0, 0, 0, 0), "b": (100, 0, 0, 0)})
    assert len(far) == 0


def test_no_prior_every_pair_full_circle():
    df = candidate_pairs(["A", "B", "C"], reach={"A": 8.0, "B": 25.0, "C": 30.0},
                         search=(5.0, 1.25, 60.0))
    assert len(df) == 3 and (df.source == "no_prior").all()
    assert (df.hheading_deg == 180.0).all() and (df.cheading_deg == 0.0).all()
    assert (df.hz == 1.25).all()
    hx = dict(zip(zip(df.scan, df.reference, strict=True), df.hx, strict=True))
    assert hx[("B", "A")] == 8.0 and hx[("C", "A")] == 8.0 and hx[("C", "B")] == 20.0
