"""Branch-and-bound registration (spec 6.3-6.7, 13.2-13.7)."""

from __future__ import annotations

import numpy as np
import pytest

from forestmap_assets.core.registration.branch_and_bound import KdEvaluator, exhaustive_search
from forestmap_assets.core.registration.register import register_pair
from forestmap_assets.core.registration.score import ScoreModel
from forestmap_assets.core.registration.score_field import ReferenceField
from forestmap_assets.core.registration.search_lattice import SearchLattice
from forestmap_assets.core.registration.submaps import build_submap, submap_points
from forestmap_assets.params import RegistrationParams
from forestmap_assets.sim.stem_layouts import stem_pair


def test_score_constants():
    m = ScoreModel(0.035, 0.3, 0.3)
    got = m.log_p(np.array([0.0, 0.035, 0.07, 0.3, np.inf]))
    np.testing.assert_allclose(got, [1.2295, 0.7295, -0.7705, -34.30, -34.66], atol=6e-3)
    assert np.isclose(m.ln_p0, 1.2295, atol=1e-4) and np.isclose(m.ln_k1, -34.657, atol=1e-3)
    assert m.log_p(m.cap_m) == m.ln_k1 and m.log_p(m.cap_m * 0.9) > m.ln_k1


def _rotz(h):
    c, s = np.cos(h), np.sin(h)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def test_bounds_dominate_scores_inside_cells():
    """Spec 13.3: Bound(C) >= score anywhere in C, for the plain and the per-axis bound."""
    rng = np.random.default_rng(0)
    ref = rng.uniform(-3, 3, (300, 3))
    scan = ref[:150] + rng.normal(0, 0.02, (150, 3))
    model = ScoreModel()
    field = ReferenceField(ref, model)
    kd = KdEvaluator(ref, model)
    d_xy = np.hypot(scan[:, 0], scan[:, 1])
    for _ in range(12):
        c = np.r_[rng.normal(0, 0.05, 3), rng.normal(0, 0.02)]
        e = rng.uniform(0.005, 0.08, 4) * np.array([1, 1, 1, 0.3])
        rot = 2 * d_xy * np.sin(e[3] / 2)
        delta = np.linalg.norm(e[:3]) + rot
        _, b_fast = field.evaluate(c[None], scan, delta, rot=rot, e_box=e[:3])
        _, b_kd = kd(c[None], scan, delta)
        inside = c + rng.uniform(-1, 1, (300, 4)) * e
        s_in, _ = kd(inside, scan, np.zeros(len(scan)), bound=False)
        assert s_in.max() <= b_fast[0] + 1e-9 and s_in.max() <= b_kd[0] + 1e-9
        s_fast, _ = field.evaluate(inside[:20], scan, np.zeros(len(scan)), bound=False)
        np.testing.assert_allclose(s_fast, s_in[:20], rtol=1e-10)  # exact scores


def _small_problem(rng, kind):
    if kind == "symmetric":  # a square of four vertical stems: 90-degree symmetric
        g = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], float) * 1.5
        z = np.arange(0, 1.0, 0.05)
        ref = np.vstack([np.column_stack([np.full_like(z, x), np.full_like(z, y), z]) for x, y in g])
    else:
        ref = np.vstack([np.column_stack([np.full(15, x), np.full(15, y), np.arange(15) * 0.05])
                         for x, y in rng.uniform(-3, 3, (5, 2))])
    truth = np.array([0.07, -0.05, 0.03, np.radians(4.0)])
    scan = (ref - truth[:3]) @ _rotz(-truth[3]).T + rng.normal(0, 0.01, ref.shape)
    if kind == "outliers":
        scan = np.vstack([scan[::2], rng.uniform(-3, 3, (25, 3))])
    return scan, ref


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["plain", "outliers", "symmetric"])
def test_branch_and_bound_equals_exhaustive(kind):
    """Spec 13.4: the search returns the final-lattice maximum, for both evaluators."""
    rng = np.random.default_rng({"plain": 1, "outliers": 2, "symmetric": 3}[kind])
    scan, ref = _small_problem(rng, kind)
    params = RegistrationParams(final_cell_m=0.05)
    box = (0.2, 0.2, 0.1, 10.0) if kind != "symmetric" else (0.2, 0.2, 0.1, 100.0)
    centre = (0.0, 0.0, 0.0, 0.0)
    poses, scores = exhaustive_search(scan, ref, centre, box, params)
    for method, bound in (("fast", "cell"), ("thesis", "cell"), ("fast", "lattice")):
        r = register_pair(scan, ref, centre, box, params, method=method, bound=bound)
        assert r.ok
        assert np.isclose(r.peak_score, scores.max(), rtol=1e-10, atol=1e-9)
        winners = poses[scores >= scores.max() - 1e-6]
        assert np.min(np.abs(winners - np.array(r.peak)).sum(1)) < 1e-6
        if bound == "lattice":  # every lattice pose scoring within the margin survives
            near = poses[scores >= scores.max() - 10.0]
            last = r.levels[r.levels.level == r.levels.level.max()]
            got = last[["dx", "dy", "dz", "dh_deg"]].to_numpy()
            for q in near:
                d = np.abs(got - q)
                d[:, 3] = np.minimum(d[:, 3], 360 - d[:, 3])
                assert d.sum(1).min() < 1e-6


def _stem_points(seed, **kw):
    pair = stem_pair(seed=seed, **kw)
    pa = submap_points(build_submap(pair.cylinders_a, None))
    pb = submap_points(build_submap(pair.cylinders_b, None))
    return pa, pb, np.array(pair.truth)


def _err(result, truth):
    e = np.array(result.peak) - truth
    e[3] = (e[3] + 180) % 360 - 180
    return e


def test_stem_layout_from_poor_prior():
    """Spec 13.6: prior off by 4.5 m and 32 deg in a +-5 m, +-1.25 m, +-60 deg box."""
    pa, pb, truth = _stem_points(1)
    off = np.array([4.5 * np.cos(0.7), 4.5 * np.sin(0.7), 0.3, 32.0])
    r = register_pair(pb, pa, truth + off, (5.0, 5.0, 1.25, 60.0), RegistrationParams())
    e = _err(r, truth)
    assert r.ok and np.hypot(e[0], e[1]) < 0.02 and abs(e[3]) < 0.2 and abs(e[2]) < 0.3
    assert r.sigma[2] > r.sigma[0]  # vertical stems constrain z weakly (spec 6.5)
    assert set(r.levels.level) == set(range(r.levels.level.max() + 1))
    final = r.levels[r.levels.level == r.levels.level.max()]
    # lattice bound (default): a final cell's bound is (a table-rounded upper bound of) its
    # score; the best cell's cloud is grown to every connected lattice cell within cloud_margin
    # (240) of the best
    assert len(final) >= r.cloud_cells > 1
    assert (final.bound >= final.score - 1e-6).all()
    assert (final.score >= r.peak_score - 240.0 - 1e-6).all() and final.score.max() == r.peak_score
    assert 0 < r.peak_mass_share <= 1


def test_stem_layout_without_prior():
    """No prior heading: the full circle (DESIGN.md 2)."""
    pa, pb, truth = _stem_points(4, n_trees=30, half_extent_m=9.0, offset=(2.0, 1.5, 0.1, 150.0),
                                 max_range_m=10.0)
    r = register_pair(pb, pa, (0, 0, 0, 0), (4.0, 4.0, 0.5, 180.0), RegistrationParams())
    e = _err(r, truth)
    assert r.ok and np.hypot(e[0], e[1]) < 0.02 and abs(e[3]) < 0.2


def test_ambiguous_row_of_stems_gives_hypotheses():
    """Spec 13.7: equally spaced stems -> shifted alignments survive as secondary hypotheses."""
    z = np.arange(0.0, 1.5, 0.05)
    row = lambda xs: np.vstack([np.column_stack([np.full_like(z, x), np.zeros_like(z), z])  # noqa: E731
                                for x in xs])
    ref = row(np.arange(-9.0, 9.1, 3.0))
    scan = row([-3.0, 0.0, 3.0])
    r = register_pair(scan, ref, (0.0, 0.0, 0.0, 0.0), (4.0, 1.0, 0.3, 10.0), RegistrationParams())
    assert r.ok and len(r.hypotheses) >= 2
    peaks = np.sort(np.r_[r.peak[0], r.hypotheses.peak_dx.to_numpy()[:2]])
    np.testing.assert_allclose(peaks, [-3.0, 0.0, 3.0], atol=0.05)
    assert np.allclose(r.hypotheses.peak_score[:2], r.peak_score)
    assert r.peak_mass_share < 0.4


def test_empty_submaps_fail_cleanly():
    pts = np.random.default_rng(0).uniform(-1, 1, (20, 3))
    for scan, ref in ((np.empty((0, 3)), pts), (pts, np.empty((0, 3)))):
        r = register_pair(scan, ref, (0, 0, 0, 0), (1, 1, 1, 10))
        assert r.status == "failed" and "no registration points" in r.reason
        assert np.isnan(r.peak_score)


def test_lattice_levels_halve_to_final_cell():
    """Spec 13.5: +-5 m halves to 0.0195 m; +-180 deg matches the metric cell at d_bar."""
    lat = SearchLattice.build((0, 0, 0, 0), (5.0, 5.0, 1.25, 180.0), 0.02, 6.5)
    np.testing.assert_allclose(lat.step[:3], [10 / 512, 10 / 512, 2.5 / 128])
    assert lat.wrap and lat.n[3] * lat.step[3] == pytest.approx(2 * np.pi)
    assert lat.step[3] * 6.5 <= 0.02
    assert len(lat.schedule()) == int(np.log2(lat.n).sum())


@pytest.mark.slow
def test_first_hypotheses_change_speed_not_result():
    """Voting and seeds only raise the initial best score: same lattice maximum without them."""
    pa, pb, truth = _stem_points(2, n_trees=25, half_extent_m=8.0, max_range_m=9.0)
    box = (1.0, 1.0, 0.3, 8.0)
    centre = truth + np.array([0.4, -0.3, 0.1, 3.0])
    params = RegistrationParams(final_cell_m=0.04)
    runs = [register_pair(pb, pa, centre, box, params, vote=v, seeds=s, tight_bound=t)
            for v, s, t in ((True, None, True), (False, None, False), (False, [centre], True))]
    for r in runs[1:]:
        assert r.peak_score == pytest.approx(runs[0].peak_score, rel=1e-12, abs=1e-9)
        np.testing.assert_allclose(r.peak, runs[0].peak, atol=1e-9)
    assert runs[0].n_cells_evaluated <= runs[1].n_cells_evaluated


def test_chunked_evaluation_gives_the_same_search(monkeypatch):
    """Memory-bounded chunks of live points (and a best raised chunk by chunk) change nothing."""
    import forestmap_assets.core.registration.fast_search as reg

    pa, pb, truth = _stem_points(3, n_trees=20, half_extent_m=7.0, max_range_m=8.0)
    args = (pb, pa, truth + np.array([0.3, 0.2, 0.1, 2.0]), (0.6, 0.6, 0.3, 5.0),
            RegistrationParams(final_cell_m=0.04))
    whole = register_pair(*args)
    monkeypatch.setattr(reg, "LIVE_CHUNK", 3000)
    chunked = register_pair(*args)
    assert chunked.peak_score == whole.peak_score and chunked.peak == whole.peak
    assert chunked.cloud_cells == whole.cloud_cells


def test_stem_voting_finds_the_alignment():
    from forestmap_assets.core.registration.stem_voting import vote_alignments

    pa, pb, truth = _stem_points(5)
    hyp = vote_alignments(pb, pa, (0, 0, 0, 0), (6.0, 6.0, 1.0, 180.0))
    e = hyp[0] - truth
    e[3] = (e[3] + 180) % 360 - 180
    assert np.hypot(e[0], e[1]) < 0.4 and abs(e[3]) < 2.0


def test_ambiguous_search_stops_at_cell_budget():
    """A single short stem against a stand: every stem matches it at any heading; the search
    gives up with an 'ambiguous' failure instead of refining a huge cloud."""
    pa, _, _ = _stem_points(6)
    z = np.arange(0.0, 1.0, 0.05)
    one = np.column_stack([np.full_like(z, 2.0), np.zeros_like(z), z])
    r = register_pair(one, pa, (0, 0, 0, 0), (8.0, 8.0, 0.5, 180.0), RegistrationParams(),
                      max_cells=2000)
    assert r.status == "failed" and "ambiguous" in r.reason


def test_fast_search_corridor_pair_has_a_result():
    """Regression: a corridor pair whose last level raised the best score inside the live
    chunks used to hand mismatched live lists to the exact kernel (garbage scores, segfault)."""
    from pathlib import Path

    from forestmap_assets.params import resolve_params

    d = np.load(Path(__file__).parents[1] / "data" / "corridor_pair.npz")
    reg = resolve_params("indoor").registration
    r = register_pair(d["scan"], d["ref"], tuple(d["centre"]), tuple(d["half"]), reg)
    assert r.status == "ok"
    assert r.cloud_cells > 0 and np.isfinite(r.peak_score)


def test_field_gives_exact_nearest_distances_on_voxel_faces():
    """The voxel candidate lists give the k-d tree's exact scores, also for queries on voxel
    faces and corners; the live-point evaluation's quick score is a lower bound of the exact
    score and its bound dominates it."""
    rng = np.random.default_rng(3)
    ref = rng.uniform(-2, 2, (400, 3))
    model = ScoreModel()
    field = ReferenceField(ref, model)
    kd = KdEvaluator(ref, model)
    lo = field.f_origin + field.f_s * np.floor((ref.min(0) - field.f_origin) / field.f_s)
    grid = lo + field.f_s * rng.integers(0, 40, (500, 3))  # voxel corners
    face = grid + np.array([0.5, 0.0, 0.5]) * field.f_s  # and faces
    scan = np.vstack([grid, face, rng.uniform(-2.2, 2.2, (500, 3))])
    s_fast, _ = field.evaluate(np.zeros((1, 4)), scan, bound=False)
    s_kd, _ = kd(np.zeros((1, 4)), scan, np.zeros(len(scan)), bound=False)
    np.testing.assert_allclose(s_fast, s_kd, rtol=1e-12)
    d_xy = np.hypot(scan[:, 0], scan[:, 1])
    n = len(scan)
    for e in ([0.01, 0.01, 0.01, 0.001], [0.05, 0.02, 0.03, 0.004], [0.12, 0.12, 0.12, 0.01]):
        e = np.array(e)
        poses = rng.normal(0, 0.02, (5, 4))
        b, s, *_ = field.eval_live(poses, np.zeros(5, np.int64), np.array([0, n], np.int64),
                                   np.arange(n, dtype=np.int32), scan, d_xy, e, True)
        delta = np.linalg.norm(e[:3]) + 2 * d_xy * np.sin(e[3] / 2)
        s_kd, _ = kd(poses, scan, delta, bound=False)
        assert np.all(s <= s_kd + 1e-9) and np.all(s >= s_kd - 0.01 * n)  # quick score: table
        assert np.all(b >= s_kd - 1e-9)  # the bound dominates the score at the cell's pose


def test_reference_field_is_reused_for_the_same_reference():
    from forestmap_assets.core.registration.fast_search import reference_field

    rng = np.random.default_rng(4)
    ref = rng.uniform(-2, 2, (200, 3))
    model = ScoreModel()
    a = reference_field(ref, model)
    assert reference_field(ref.copy(), model) is a
    moved = ref.copy()
    moved[0, 0] += 1e-6
    assert reference_field(moved, model) is not a
    assert reference_field(ref, ScoreModel(sigma_m=0.05)) is not a


def test_asymmetric_box_and_parent_terms_bound_the_scores():
    """The per-axis bound over an asymmetric offset box (the lattice bound's cells) dominates
    the exact score at every pose in the box, also when it is tightened by (and stopped early
    on) the parent cell's per-point terms."""
    rng = np.random.default_rng(5)
    ref = rng.uniform(-3, 3, (300, 3))
    scan = ref[:150] + rng.normal(0, 0.02, (150, 3))
    model = ScoreModel()
    field = ReferenceField(ref, model)
    kd = KdEvaluator(ref, model)
    n = len(scan)
    d_xy = np.hypot(scan[:, 0], scan[:, 1])
    root_off, root_idx = np.array([0, n], np.int64), np.arange(n, dtype=np.int32)
    for _ in range(10):
        c = np.r_[rng.normal(0, 0.03, 3), rng.normal(0, 0.01)]
        e = rng.uniform(0.005, 0.06, 4) * np.array([1, 1, 1, 0.2])
        lo = -e * rng.uniform(0, 1, 4)
        hi = e * rng.uniform(0, 1, 4)
        # parent: the symmetric box +-e, then the child: [lo, hi] (inside it)
        b_p, _, off_p, cnt_p, live_p, t_p = field.eval_live(
            c[None], np.zeros(1, np.int64), root_off, root_idx, scan, d_xy, e, True, lo=-e, hi=e)
        off_p = np.r_[0, np.cumsum(cnt_p)].astype(np.int64)
        b, s, *_ = field.eval_live(c[None], np.zeros(1, np.int64), off_p, live_p[:cnt_p[0]],
                                   scan, d_xy, e, True, lo=lo, hi=hi, par_terms=t_p[:cnt_p[0]],
                                   par_bound=b_p)
        inside = c + lo + rng.uniform(0, 1, (400, 4)) * (hi - lo)
        inside = np.vstack([inside, c + lo, c + hi])
        s_in, _ = kd(inside, scan, np.zeros(n), bound=False)
        assert s_in.max() <= b[0] + 1e-9 and b[0] <= b_p[0] + 1e-9
        # early stop: with a threshold above the bound the cell is reported below it
        b_stop, s_stop, *_ = field.eval_live(
            c[None], np.zeros(1, np.int64), off_p, live_p[:cnt_p[0]], scan, d_xy, e, True, lo=lo,
            hi=hi, par_terms=t_p[:cnt_p[0]], par_bound=b_p, thresh=b[0] + 1.0)
        assert b_stop[0] < b[0] + 1.0 and b_stop[0] >= s_in.max() - 1e-9


def test_lattice_search_grows_the_cloud_and_keeps_the_maximum():
    """bound='lattice': the lattice maximum of exhaustive search, with the heading halved by
    the thesis rule or earlier (``heading_split_scale``); the final cloud holds every lattice
    cell connected to the peak (80 neighbours) that scores within ``cloud_margin`` of it."""
    from forestmap_assets.core.registration.cell_clouds import lattice_components

    rng = np.random.default_rng(1)
    scan, ref = _small_problem(rng, "plain")
    params = RegistrationParams(final_cell_m=0.05)
    box, centre = (0.2, 0.2, 0.1, 10.0), (0.0, 0.0, 0.0, 0.0)
    poses, scores = exhaustive_search(scan, ref, centre, box, params)
    d_bar = float(np.mean(np.hypot(scan[:, 0], scan[:, 1])))
    lat = SearchLattice.build(centre, box, params.final_cell_m, d_bar)
    idx = np.array(np.meshgrid(*[np.arange(v) for v in lat.n], indexing="ij")).reshape(4, -1).T
    margin = 60.0
    near = scores >= scores.max() - margin
    _, lab = lattice_components(idx[near], lat.n, lat.wrap, 80)
    peak_comp = lab[int(np.argmax(scores[near]))]
    want = poses[near][lab == peak_comp]
    for split in (1.0, 2.0):
        r = register_pair(scan, ref, centre, box, params, bound="lattice", cloud_margin=margin,
                          heading_split_scale=split)
        assert np.isclose(r.peak_score, scores.max(), rtol=1e-10, atol=1e-9)
        last = r.levels[r.levels.level == r.levels.level.max()]
        got = last[["dx", "dy", "dz", "dh_deg"]].to_numpy()
        for q in want:
            d = np.abs(got - q)
            d[:, 3] = np.minimum(d[:, 3], 360 - d[:, 3])
            assert d.sum(1).min() < 1e-6
        assert r.cloud_cells >= len(want)


def test_candidate_lists_are_sorted_by_their_distance_from_the_voxel():
    """Each voxel's candidates come in ascending order of their distance from the voxel's box,
    and that stored distance never exceeds the distance to any position inside the voxel (the
    nearest-distance loops stop on it); the scores stay the k-d tree's for any voxel size."""
    rng = np.random.default_rng(6)
    ref = rng.uniform(-2, 2, (300, 3))
    model = ScoreModel()
    kd = KdEvaluator(ref, model)
    scan = rng.uniform(-2.3, 2.3, (2000, 3))
    s_kd, _ = kd(np.zeros((1, 4)), scan, np.zeros(len(scan)), bound=False)
    for fine in (0.1, 0.2, 0.35):
        field = ReferenceField(ref, model, fine_m=fine)
        off, idx, lb = field.cand_off, field.cand_idx, field.cand_lb
        n_vox = np.diff(off)
        same = np.repeat(np.arange(len(n_vox)), n_vox)
        assert np.all((np.diff(lb) >= 0) | (same[1:] != same[:-1]))
        # positions inside the voxels of the scan's points: never nearer than the stored distance
        v_of = np.floor((scan - field.f_origin) / field.f_s).astype(int)
        for q, (ix, iy, iz) in zip(scan[:300], v_of[:300], strict=True):
            nb1, nb2 = field.nb_shape[1], field.nb_shape[2]
            b = field.bmap[((ix >> 3) * nb1 + (iy >> 3)) * nb2 + (iz >> 3)]
            if b < 0:
                continue
            v = b * 512 + (((ix & 7) << 6) | ((iy & 7) << 3) | (iz & 7))
            dist = np.linalg.norm(ref[idx[off[v]:off[v + 1]]] - q, axis=1)
            assert np.all(lb[off[v]:off[v + 1]] <= dist)
        s_fast, _ = field.evaluate(np.zeros((1, 4)), scan, bound=False)
        np.testing.assert_allclose(s_fast, s_kd, rtol=1e-12)
