"""Candidate screening without a prior (inferred, issue 17): stem-layout scores of scan pairs."""

from __future__ import annotations

import numpy as np
import pandas as pd

from forestmap_assets.core.registration.candidates import candidate_pairs
from forestmap_assets.core.registration.screening import (
    keep_best,
    screen_pair,
    screen_scores,
    stems_from_cylinders,
)


def _forest(rng, size=(60.0, 60.0), density=0.06):
    n = rng.poisson(density * size[0] * size[1])
    xy = rng.uniform((0, 0), size, (n, 2))
    return np.column_stack([xy, rng.uniform(0.07, 0.3, n)])


def _view(rng, forest, centre, reach=14.0, drop=0.2, noise_m=0.03):
    """Stems a scanner at ``centre`` sees, in its own random frame; and that frame's pose."""
    d = np.hypot(*(forest[:, :2] - centre).T)
    seen = forest[(d < reach) & (rng.random(len(forest)) > drop)]
    h = rng.uniform(-np.pi, np.pi)
    c, s = np.cos(h), np.sin(h)
    local = (seen[:, :2] - centre) @ np.array([[c, -s], [s, c]])  # R(-h) (p - centre)
    local += rng.normal(0, noise_m, local.shape)
    r = seen[:, 2] + rng.normal(0, 0.01, len(seen))
    return np.column_stack([local, r]), (centre[0], centre[1], np.degrees(h))


def _relative(scan_pose, ref_pose):
    d = np.subtract(scan_pose[:2], ref_pose[:2])
    h = np.radians(ref_pose[2])
    c, s = np.cos(h), np.sin(h)
    return c * d[0] + s * d[1], -s * d[0] + c * d[1], (scan_pose[2] - ref_pose[2] + 180) % 360 - 180


def test_same_layout_scores_far_above_different_layouts():
    rng = np.random.default_rng(3)
    forest, other = _forest(rng), _forest(rng)
    a, pa = _view(rng, forest, np.array([30.0, 30.0]))
    b, pb = _view(rng, forest, np.array([36.0, 33.0]))  # partial overlap, 6.7 m apart
    c, _ = _view(rng, other, np.array([33.0, 31.0]))
    same, motion = screen_pair(a, b)
    diff, _ = screen_pair(a, c)
    assert same >= 10 and same >= 3 * max(diff, 1)
    want = _relative(pb, pa)
    assert np.hypot(motion[0] - want[0], motion[1] - want[1]) < 0.15
    assert abs((motion[2] - want[2] + 180) % 360 - 180) < 1.5


def _strip(seed, n=8, step=7.0):
    rng = np.random.default_rng(seed)
    forest = _forest(rng, size=(20.0 + step * n, 30.0))
    views = [_view(rng, forest, np.array([10.0 + step * k, 15.0]))[0] for k in range(n)]
    return {f"s{k}": v for k, v in enumerate(views)}


def test_chain_of_views_keeps_every_true_neighbour():
    for seed in (0, 1):
        stems = _strip(seed)
        ids = list(stems)
        scores = screen_scores(stems)
        kept = keep_best(scores, 2)
        assert len(kept) <= 3 * len(ids)
        for k in range(len(ids) - 1):
            assert (ids[k + 1], ids[k]) in kept, (seed, k)


def test_screening_beats_random_choice():
    """With one partner per scan, the screened set holds every neighbour pair of the strip; a
    random choice of the same size almost never does (fails if screening were random)."""
    stems = _strip(5)
    ids = list(stems)
    scores = screen_scores(stems)
    truth = {(ids[k + 1], ids[k]) for k in range(len(ids) - 1)}
    kept = keep_best(scores, 1)
    assert truth <= kept
    rng = np.random.default_rng(0)
    shuffled = scores.assign(score=rng.permutation(len(scores)))
    assert not truth <= keep_best(shuffled, 1)
    neighbour = scores.set_index(["scan", "reference"])["score"]
    far = [v for (s, r), v in neighbour.items() if abs(int(s[1:]) - int(r[1:])) >= 4]
    assert min(neighbour[list(truth)]) > max(far) and np.mean(neighbour[list(truth)]) > 3 * np.mean(far)


def test_candidate_pairs_screened_linear_and_small_campaigns_whole():
    stems = _strip(2, n=10)
    ids = list(stems)
    df = candidate_pairs(ids, reach={s: 12.0 for s in ids}, stems=stems, screen_keep=2)
    assert (df.source == "no_prior").all() and len(df) <= 3 * len(ids) and len(df) < 45
    assert "screen_score" in df and (df.screen_score >= 0).all()
    got = set(zip(df.scan, df.reference, strict=True))
    assert all((ids[k + 1], ids[k]) in got for k in range(len(ids) - 1))
    whole = candidate_pairs(ids, reach={s: 12.0 for s in ids}, stems=stems, screen_keep=0)
    assert len(whole) == 45
    small = candidate_pairs(ids[:3], reach={s: 12.0 for s in ids}, stems=stems, screen_keep=2)
    assert len(small) == 3


def test_stems_from_cylinders_merges_segments_of_one_stem():
    cyl = pd.DataFrame({
        "x0": [1.0, 1.02, 5.0], "y0": [2.0, 2.0, 5.0], "z0": [-1.0, 0.5, -0.5],
        "x1": [1.0, 1.04, 5.0], "y1": [2.0, 2.0, 5.0], "z1": [0.4, 2.0, 1.5],
        "radius_m": [0.2, 0.18, 0.1],
    })
    stems = stems_from_cylinders(cyl)
    assert stems.shape == (2, 3)
    first = stems[np.argmin(stems[:, 0])]
    assert abs(first[0] - 1.0) < 0.05 and 0.18 <= first[2] <= 0.2


def test_unplaced_scans_are_retried_against_their_next_best_partners():
    from forestmap_assets.core.registration.candidates import retry_candidates

    stems = _strip(1)
    ids = list(stems)
    searched = [(ids[k + 1], ids[k]) for k in range(len(ids) - 1)]
    cand = pd.DataFrame({"scan": [s for s, _ in searched], "reference": [r for _, r in searched]})
    status = ["accepted"] * len(searched)
    status[5] = "rejected"  # s6-s5 failed: s6 and s7 are unplaced
    regs = cand.assign(status=status)
    extra = retry_candidates(ids, cand, regs, stems, keep=1, reach={s: 14.0 for s in ids})
    assert set(zip(extra.scan, extra.reference, strict=True)) == {("s6", "s4"), ("s7", "s5")}
    assert (extra.hheading_deg == 180.0).all() and (extra.screen_score >= 5).all()
    # every scan placed and every link on a loop (the chain and the pairs two views apart): none
    loops = pd.concat([cand, pd.DataFrame({"scan": ids[2:], "reference": ids[:-2]})], ignore_index=True)
    none = retry_candidates(ids, loops, loops.assign(status="accepted"), stems, keep=1)
    assert len(none) == 0


def test_well_matched_pairs_are_searched_around_their_screening_motion():
    """Pairs with enough matched stems get a small box around the screening motion (the truth
    inside it); ``widened`` gives the same pairs the no-prior box for a second search."""
    from forestmap_assets.core.registration.candidates import widened

    rng = np.random.default_rng(3)
    forest = _forest(rng)
    a, pa = _view(rng, forest, np.array([30.0, 30.0]))
    b, pb = _view(rng, forest, np.array([36.0, 33.0]))
    df = candidate_pairs(["a", "b"], reach={"a": 14.0, "b": 14.0}, stems={"a": a, "b": b}, screen_keep=2,
                         screen_centre_min=4, screen_box=(1.0, 10.0))
    row = df.iloc[0]
    assert row.source == "screened" and row.hx == 1.0 and row.hheading_deg == 10.0
    want = _relative(pb, pa)
    assert np.hypot(row.cx - want[0], row.cy - want[1]) < 0.15
    assert abs((row.cheading_deg - want[2] + 180) % 360 - 180) < 1.5
    again = widened(df, reach={"a": 14.0, "b": 14.0})
    assert len(again) == 1 and again.iloc[0].source == "no_prior" and again.iloc[0].hheading_deg == 180.0
    assert again.iloc[0].cx == 0.0 and again.iloc[0].hx == 14.0
    # unrelated layouts: too few matches, the no-prior box
    c, _ = _view(rng, _forest(rng), np.array([33.0, 31.0]))
    other = candidate_pairs(["a", "c"], reach={"a": 14.0, "c": 14.0}, stems={"a": a, "c": c}, screen_keep=2,
                            screen_centre_min=8, screen_box=(1.0, 10.0))
    assert other.iloc[0].source == "no_prior" and other.iloc[0].hheading_deg == 180.0


def test_large_campaigns_keep_more_partners():
    """Campaigns of more than ``screen_large_scans`` scans keep ``screen_keep_large`` partners
    (loops against the network's turning about its reference); ``screen_keep`` 0 screens none."""
    from forestmap_assets.params import RegistrationParams

    reg = RegistrationParams()
    assert [reg.keep_for(n) for n in (6, 12, 13, 100)] == [2, 2, 4, 4]
    assert RegistrationParams(screen_keep=0).keep_for(100) == 0
    assert RegistrationParams(screen_keep_large=6, screen_large_scans=5).keep_for(6) == 6


def test_link_graph_bridges_and_their_sides():
    from forestmap_assets.core.registration.link_graph import bridges, sides

    # two triangles joined by one link, and a tail: c-d and e-f lie on no loop
    edges = [("a", "b"), ("b", "c"), ("c", "a"), ("c", "d"), ("d", "e"), ("e", "g"), ("g", "d"), ("e", "f")]
    assert bridges(edges) == [("c", "d"), ("e", "f")]
    assert sides(edges, ("c", "d")) == ({"a", "b", "c"}, {"d", "e", "f", "g"})
    assert bridges(edges + [("b", "g")]) == [("e", "f")]
    assert bridges([("a", "b"), ("b", "c")]) == [("a", "b"), ("b", "c")] and bridges([]) == []


def test_screened_pairs_close_a_loop_over_every_link():
    """One partner a scan keeps a chain of the strip, every link on no loop; ``close_loops`` adds,
    across each, the best pair of the scores (two views apart) until every link is on a loop."""
    from forestmap_assets.core.registration.link_graph import bridges

    stems = _strip(5)
    ids = list(stems)
    scores = screen_scores(stems)
    chain = keep_best(scores, 1)
    assert len(bridges(sorted(chain))) == len(chain)
    closed = keep_best(scores, 1, close_loops=True)
    assert chain < closed and bridges(sorted(closed)) == []
    extra = closed - chain
    assert all(abs(int(s[1:]) - int(r[1:])) == 2 for s, r in extra), extra
    assert keep_best(scores, 1, close_loops=True, min_score=10_000) == chain  # nothing scores so high
    # a candidate table of the strip closes its loops the same way
    df = candidate_pairs(ids, reach={s: 14.0 for s in ids}, stems=stems, screen_keep=1)
    assert set(zip(df.scan, df.reference, strict=True)) == closed


def test_a_link_left_on_no_loop_by_a_failed_pair_is_retried_across():
    """Every scan placed, but a failed pair of the searched loop left s3-s2 on no loop: the
    best pairs across it not yet searched are retried; none when every link is on a loop."""
    from forestmap_assets.core.registration.candidates import retry_candidates, weak_links

    stems = _strip(1, n=6)
    ids = list(stems)
    searched = [("s1", "s0"), ("s2", "s1"), ("s2", "s0"), ("s3", "s2"), ("s4", "s3"), ("s5", "s4"),
                ("s5", "s3"), ("s3", "s1")]
    cand = pd.DataFrame({"scan": [s for s, _ in searched], "reference": [r for _, r in searched]})
    regs = cand.assign(status=["accepted"] * 7 + ["rejected"])  # s3-s1 failed
    assert weak_links(ids, regs) == [({"s3", "s4", "s5"}, {"s0", "s1", "s2"})]  # a tie: s3's side first
    extra = retry_candidates(ids, cand, regs, stems, keep=1, reach={s: 14.0 for s in ids})
    # the best pair across not yet searched: 7 stems, s3-s0 and s4-s2 (the earlier partner first)
    assert list(zip(extra.scan, extra.reference, strict=True)) == [("s3", "s0")]
    assert extra.screen_score.tolist() == [7.0] and (extra.hheading_deg == 180.0).all()
    two = retry_candidates(ids, cand, regs, stems, keep=2, reach={s: 14.0 for s in ids})
    assert list(zip(two.scan, two.reference, strict=True)) == [("s3", "s0"), ("s4", "s2")]
    assert weak_links(ids, cand.assign(status="accepted")) == []
    assert len(retry_candidates(ids, cand, cand.assign(status="accepted"), stems, keep=1)) == 0
