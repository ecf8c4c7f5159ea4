"""``forestmap explore``: a whole survey planned scan by scan in a virtual plot (men_spec 7.7).

The loop of the thesis (Fig. 6.3) with a surveyor instead of a robot: scan at the start, run the
pipeline (:func:`~forestmap_assets.runner.run_campaign`: features, registration, optimal map,
integrated map, trees), compute the exploration grid and the ranked next vantage positions
(:mod:`.core.exploration`), walk to the best one, scan there with the virtual scanner, and repeat
until the scan budget is spent, coverage stops improving (``min_gain``), or no position is
expected to add area while keeping enough overlap to register.

Walking (inferred): the surveyor reaches the planned position within ``walk_sigma_m`` (normal
per axis) and sets the tripod up facing away from the reference scan (the scanner's 30 deg
blind sector towards the mapped side) +-20 deg. Each new scan is paired with the planner's
reference scan and up to ``max_pairs - 1`` further scans with enough predicted common stems;
the pair's a priori alignment is the planned position with the local ground + 1.5 m and a
compass heading (error ``compass_sigma_deg``) relative to the reference's estimated pose, the
search box is sized for these errors (``use_prior=False``: no pairs, full search). Written::

    OUT/campaign.yaml, OUT/scans/<id>.npz      the campaign as it grew
    OUT/truth/poses.csv, trees.csv, stems.csv   truth in the frame of the first scan (as simulate)
    OUT/truth/plot.csv                          plot corners in that frame
    OUT/explore/steps.csv                       per scan: plan, truth, registration, coverage
    OUT/explore/step_<k>.png, proposals_<k>.csv the plan made after scan k
    OUT/outputs/                                the exports of the final map (DESIGN.md 4)

:func:`survey_positions` scans a fixed list of positions instead (the grid and random baselines
of ``benchmarks/bench_explore.py``) and runs the pipeline once at the end.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from forestmap_assets.core.exploration import ExplorationConfig
from forestmap_assets.params_men import OcclusionConfig
from forestmap_assets.sim.campaign import relative_pose, save_npz, scan_ids, visible_trees, wrap_deg
from forestmap_assets.sim.forest import (
    KIND_UNDERSTOREY,
    breast_height_table,
    make_forest,
    stems_in_frame,
)
from forestmap_assets.sim.scanner import RESOLUTION_DIVISOR, ScanPose, VirtualScanner

Progress = Callable[[str], None]
STEP_COLUMNS = [
    "step",
    "scan",
    "reference",
    "planned_x",
    "planned_y",
    "true_x",
    "true_y",
    "true_heading_deg",
    "expected_new_m2",
    "predicted_common_stems",
    "predicted_overlap",
    "path_m",
    "registered",
    "pose_error_m",
    "heading_error_deg",
    "coverage",
    "gain",
    "trees",
    "trees_with_dbh",
    "pipeline_seconds",
    "plan_seconds",
]


@dataclass
class VirtualPlot:
    """A virtual forest plot, the scanner, and the global frame (levelled frame of the first
    scan, world pose ``origin``)."""

    forest: object
    scanner: VirtualScanner
    origin: ScanPose
    plot_size: float
    _understorey_xy: np.ndarray | None = field(default=None, repr=False)

    def to_global(self, xy_world) -> np.ndarray:
        c, s = (
            np.cos(np.radians(self.origin.heading_deg)),
            np.sin(np.radians(self.origin.heading_deg)),
        )
        d = np.asarray(xy_world, dtype=np.float64).reshape(-1, 2) - [self.origin.x, self.origin.y]
        return np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])

    def to_world(self, xy_global) -> np.ndarray:
        c, s = (
            np.cos(np.radians(self.origin.heading_deg)),
            np.sin(np.radians(self.origin.heading_deg)),
        )
        g = np.asarray(xy_global, dtype=np.float64).reshape(-1, 2)
        return np.column_stack([c * g[:, 0] - s * g[:, 1], s * g[:, 0] + c * g[:, 1]]) + [
            self.origin.x,
            self.origin.y,
        ]

    def plot_polygon(self) -> np.ndarray:
        """Plot corners in the global frame."""
        h = self.plot_size / 2
        return self.to_global(np.array([[-h, -h], [h, -h], [h, h], [-h, h]]))

    def ground(self, x, y) -> np.ndarray:
        return self.forest.ground.height(
            np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        )

    def is_free(self, xy_world, clearance_m: float = 0.5) -> np.ndarray:
        """Positions (world) at least ``clearance_m`` from every stem and understorey object."""
        xy = np.asarray(xy_world, dtype=np.float64).reshape(-1, 2)
        bh = breast_height_table(self.forest.stems)
        d = np.hypot(
            xy[:, None, 0] - bh["x"].to_numpy()[None], xy[:, None, 1] - bh["y"].to_numpy()[None]
        )
        ok = (d >= bh["dbh_m"].to_numpy()[None] / 2 + clearance_m).all(axis=1)
        if self._understorey_xy is None:
            mesh = self.forest.mesh
            tri = mesh.triangles[mesh.kind == KIND_UNDERSTOREY]
            self._understorey_xy = (
                mesh.vertices[np.unique(tri.ravel()), :2] if len(tri) else np.zeros((0, 2))
            )
        if len(self._understorey_xy):
            from scipy.spatial import cKDTree

            dist, _ = cKDTree(self._understorey_xy).query(xy)
            ok &= dist >= clearance_m
        return ok

    def free_near(
        self, xy_world, rng: np.random.Generator, clearance_m: float = 0.5, max_shift_m: float = 3.0
    ) -> np.ndarray:
        """The position, or the nearest free one found on rings around it."""
        p = np.asarray(xy_world, dtype=np.float64).reshape(2)
        if self.is_free(p, clearance_m)[0]:
            return p
        for r in np.arange(0.25, max_shift_m + 1e-9, 0.25):
            ang = rng.uniform(0, 2 * np.pi) + np.arange(16) * (2 * np.pi / 16)
            cand = p + r * np.column_stack([np.cos(ang), np.sin(ang)])
            ok = self.is_free(cand, clearance_m)
            if ok.any():
                return cand[np.argmax(ok)]
        return p

    def pose_at(
        self, xy_world, heading_deg: float, rng: np.random.Generator, height_m: float = 1.5
    ) -> ScanPose:
        x, y = (float(v) for v in np.asarray(xy_world).reshape(2))
        z = float(self.ground(x, y)) + height_m + float(rng.uniform(-0.1, 0.1))
        return ScanPose(x, y, z, float(wrap_deg(heading_deg)))

    def global_pose(self, pose: ScanPose) -> np.ndarray:
        """(x, y, z, heading) of a scan in the global frame (truth)."""
        return relative_pose(pose, self.origin)


def make_plot(
    plot_size: float = 40.0,
    trees: int = 40,
    seed: int = 0,
    *,
    resolution: str = "full",
    start_xy: Sequence[float] | None = None,
    forest_kwargs: dict | None = None,
    scanner_kwargs: dict | None = None,
) -> tuple[VirtualPlot, np.random.SeedSequence]:
    """The virtual plot of ``seed`` and the seed sequence for everything that follows; the first
    scan stands at ``start_xy`` (world; default a quarter of the plot in from the south-west
    corner, inferred) with a random heading."""
    if resolution not in RESOLUTION_DIVISOR:
        raise ValueError(f"resolution: {resolution!r} is not one of {list(RESOLUTION_DIVISOR)}")
    ss_forest, ss_origin, ss_rest = np.random.SeedSequence(seed).spawn(3)
    start = np.array(
        [-plot_size / 4, -plot_size / 4] if start_xy is None else start_xy, dtype=np.float64
    )
    forest = make_forest(
        trees,
        plot_size,
        scan_xy=start[None],
        seed=np.random.default_rng(ss_forest),
        **(forest_kwargs or {}),
    )
    scanner = VirtualScanner(forest, resolution=resolution, **(scanner_kwargs or {}))
    rng = np.random.default_rng(ss_origin)
    heading = float(rng.uniform(-180.0, 180.0))
    vp = VirtualPlot(forest, scanner, ScanPose(0.0, 0.0, 0.0), plot_size)
    vp.origin = vp.pose_at(start, heading, rng)
    return vp, ss_rest


class SurveyWriter:
    """The growing campaign folder: scans, truth and ``campaign.yaml``."""

    def __init__(
        self,
        out: Path,
        vp: VirtualPlot,
        *,
        search: dict,
        rng_noise: np.random.Generator,
        params: dict | None = None,
    ):
        self.out = Path(out)
        self.vp = vp
        self.search = search
        self.params = params or {}
        self.rng_noise = rng_noise
        self.ids: list[str] = []
        self.poses: list[ScanPose] = []
        self.pairs: list[dict] = []
        self.n_visible = np.zeros(
            int(vp.forest.stems["tree_id"].max()) + 1 if len(vp.forest.stems) else 1, dtype=np.int64
        )
        for sub in ("scans", "truth", "explore"):
            (self.out / sub).mkdir(parents=True, exist_ok=True)
        pd.DataFrame(vp.plot_polygon(), columns=["x", "y"]).to_csv(
            self.out / "truth" / "plot.csv", index=False, float_format="%.6f"
        )
        stems_g = stems_in_frame(vp.forest.stems, vp.origin.origin, vp.origin.heading_deg)
        stems_g.to_csv(self.out / "truth" / "stems.csv", index=False, float_format="%.6f")
        self._trees = breast_height_table(stems_g)

    def add_scan(self, pose: ScanPose) -> str:
        sid = scan_ids(len(self.ids) + 1)[-1]
        result = self.vp.scanner.scan(pose, self.rng_noise)
        img = result.image
        arrays = {
            "range": img.range_m,
            "azimuth_deg": img.azimuth_deg,
            "elevation_deg": img.elevation_deg,
        }
        if img.intensity is not None:
            arrays["intensity"] = img.intensity
        save_npz(self.out / "scans" / f"{sid}.npz", arrays)
        self.n_visible[visible_trees(result, self.vp.forest)] += 1
        self.ids.append(sid)
        self.poses.append(pose)
        self._write_truth()
        return sid

    def add_pair(self, scan: str, reference: str, a_priori) -> None:
        self.pairs.append(
            {
                "scan": scan,
                "reference": reference,
                "a_priori": [round(float(v), 4) for v in a_priori],
            }
        )

    def _write_truth(self) -> None:
        rel = np.array([self.vp.global_pose(p) for p in self.poses])
        pd.DataFrame(
            {
                "scan": self.ids,
                "x": rel[:, 0],
                "y": rel[:, 1],
                "z": rel[:, 2],
                "heading_deg": rel[:, 3],
            }
        ).to_csv(self.out / "truth" / "poses.csv", index=False, float_format="%.6f")
        trees = self._trees.copy()
        trees["n_visible_scans"] = self.n_visible[trees["tree_id"].to_numpy()]
        trees.to_csv(self.out / "truth" / "trees.csv", index=False, float_format="%.6f")

    def write_manifest(self) -> Path:
        sc = self.vp.scanner
        doc: dict = {
            "name": self.out.resolve().name,
            "environment": "forest",
            "sensor": {"angular_step_deg": [round(float(sc.d_az), 9), round(float(sc.d_el), 9)]},
            "scans": [{"id": s, "path": f"scans/{s}.npz"} for s in self.ids],
        }
        if self.pairs:
            doc["pairs"] = self.pairs
        if self.search:
            doc["search"] = self.search
        if self.params:
            doc["params"] = self.params
        path = self.out / "campaign.yaml"
        tmp = path.with_suffix(".yaml.tmp")
        with open(tmp, "w") as fh:
            yaml.safe_dump(doc, fh, sort_keys=False, default_flow_style=None)
        tmp.replace(path)
        return path


def _prior_pose(xy_global, ground_z: float, heading_global: float, height_m: float = 1.5) -> tuple:
    return (
        float(xy_global[0]),
        float(xy_global[1]),
        float(ground_z) + height_m,
        float(wrap_deg(heading_global)),
    )


@dataclass
class SurveyMap:
    """What the pipeline knows after a run, with the plan made from it."""

    plan: object
    elevation: object
    stems: np.ndarray
    scans: pd.DataFrame  # registered scans, global estimated poses
    poses: pd.DataFrame  # poses.csv rows
    trees: pd.DataFrame


class SurfaceCache:
    """Observed-surface voxels per scan (range images do not change once scanned)."""

    def __init__(self, config: OcclusionConfig | None = None):
        self.config = config or OcclusionConfig()
        self._cache: dict[tuple[str, str], dict] = {}

    def get(self, campaign, sid: str) -> dict:
        from forestmap_assets.access import load_asset
        from forestmap_assets.assets.exploration import scan_surface

        key = (campaign.key, sid)
        if key not in self._cache:
            bundle = scan_surface(
                load_asset("range_images", campaign=campaign, scan=sid), self.config
            )
            bundle.pop("_mask", None)
            self._cache[key] = bundle
        return self._cache[key]


def read_map(
    folder: Path,
    config: ExplorationConfig,
    cache: SurfaceCache,
    *,
    current: str | None = None,
    fallback_xy=None,
) -> SurveyMap:
    """Load the stored map of the campaign and plan from it; the surveyor stands at scan
    ``current`` (its estimated position), or at ``fallback_xy`` when it is not registered."""
    from forestmap_assets.access import load_asset
    from forestmap_assets.assets.exploration import plan_from_map
    from forestmap_assets.io.campaign import load_campaign

    campaign = load_campaign(folder)
    poses = load_asset("optimal_map", campaign=campaign)["poses"]
    integrated = load_asset("integrated_map", campaign=campaign)
    trees = load_asset("tree_list", campaign=campaign)
    scans = integrated["scans"]
    surfaces = {sid: cache.get(campaign, sid) for sid in scans["scan"].astype(str)}
    here = scans[scans["scan"].astype(str) == current] if current is not None else scans.iloc[:0]
    current_xy = here[["x", "y"]].to_numpy(float)[0] if len(here) else fallback_xy
    plan, elevation, stems = plan_from_map(
        surfaces, integrated, trees, config, current_xy=current_xy
    )
    return SurveyMap(plan, elevation, stems, scans, poses, trees)


class ExploreError(ValueError):
    """The pipeline failed during a survey (one line: stage and reason)."""


def _run(folder: Path, progress: Progress) -> float:
    """Run the pipeline on the campaign as it stands; raise :class:`ExploreError` on a failure."""
    from forestmap_assets.runner import run_campaign

    t0 = time.perf_counter()
    summary = run_campaign(folder, progress=lambda m: progress(f"    {m.strip()}"))
    if summary.failures:
        stage, scan, reason = summary.failures[0]
        raise ExploreError(f"pipeline failed in {stage}{f'[{scan}]' if scan else ''}: {reason}")
    return time.perf_counter() - t0


def _registration_check(folder: Path, poses: pd.DataFrame, sid: str) -> tuple[bool, float, float]:
    from forestmap_assets.sim.evaluate import pose_errors

    truth = pd.read_csv(folder / "truth" / "poses.csv")
    row = poses[poses["scan"] == sid]
    if row.empty or not bool(row["registered"].iloc[0]):
        return False, np.nan, np.nan
    pe = pose_errors(poses.assign(registered=poses["registered"].astype(bool)), truth)
    pe = pe[pe["scan"] == sid]
    return True, float(pe["exy"].iloc[0]), float(abs(pe["eheading_deg"].iloc[0]))


def _tree_counts(folder: Path, trees: pd.DataFrame, match_m: float = 0.5) -> tuple[int, int, float]:
    """Truth trees matched by a mapped tree, those with a DBH, and the DBH RMSE (m)."""
    from forestmap_assets.sim.evaluate import match_trees

    truth = pd.read_csv(folder / "truth" / "trees.csv")
    m = match_trees(trees, truth, match_m)
    found = m["est_x"].notna()
    dbh = m["est_dbh_m"].notna()
    err = (m.loc[dbh, "est_dbh_m"] - m.loc[dbh, "dbh_m"]).to_numpy()
    return int(found.sum()), int(dbh.sum()), float(np.sqrt(np.mean(err**2))) if err.size else np.nan


@dataclass
class ExploreResult:
    folder: Path
    steps: pd.DataFrame
    coverage: float
    stop_reason: str
    trees: int
    trees_with_dbh: int
    dbh_rmse_m: float
    path_m: float
    seconds: float
    positions_world: np.ndarray

    @property
    def all_registered(self) -> bool:
        return bool(self.steps["registered"].all())


def _save_plan(out: Path, k: int, sm: SurveyMap, title: str) -> None:
    from forestmap_assets.core.exploration import exploration_figure

    sm.plan.proposals.to_csv(
        out / "explore" / f"proposals_{k:02d}.csv", index=False, float_format="%.4f"
    )
    fig = exploration_figure(sm.plan, sm.elevation, sm.stems, sm.scans, title=title)
    fig.savefig(out / "explore" / f"step_{k:02d}.png", dpi=90)



def _plot_and_streams(plot_size, trees, seed, resolution, start_xy, forest_kwargs, scanner_kwargs):
    """The virtual plot of ``seed`` and its random streams: scanner noise (seed sequence),
    walking and a priori (generators); the same for :func:`explore` and
    :func:`survey_positions`, so both survey one plot alike."""
    vp, ss = make_plot(
        plot_size,
        trees,
        seed,
        resolution=resolution,
        start_xy=start_xy,
        forest_kwargs=forest_kwargs,
        scanner_kwargs=scanner_kwargs,
    )
    ss_walk, ss_noise, ss_prior = ss.spawn(3)
    return vp, ss_noise, np.random.default_rng(ss_walk), np.random.default_rng(ss_prior)

def explore(
    out,
    *,
    plot_size: float = 40.0,
    trees: int = 40,
    seed: int = 0,
    budget: int = 8,
    resolution: str = "full",
    strategy: str = "coverage",
    config: ExplorationConfig | None = None,
    start_xy: Sequence[float] | None = None,
    min_gain: float = 0.01,
    min_expected_m2: float = 2.0,
    walk_sigma_m: float = 0.3,
    compass_sigma_deg: float = 5.0,
    use_prior: bool = True,
    max_pairs: int = 2,
    progress: Progress | None = None,
    forest_kwargs: dict | None = None,
    scanner_kwargs: dict | None = None,
    export_kwargs: dict | None = None,
    campaign_params: dict | None = None,
) -> ExploreResult:
    """Plan and simulate a survey of a virtual plot (module docstring); deterministic per seed.

    ``export_kwargs`` go to :func:`~forestmap_assets.exports.write_exports` (the final map's
    exports in ``OUT/outputs``); ``campaign_params``: the ``params`` section of the campaign's
    ``campaign.yaml`` (per-stage overrides, DESIGN.md 2.1)."""
    say = progress or (lambda _m: None)
    if budget < 1:
        raise ValueError("budget: need at least one scan")
    t_start = time.perf_counter()
    out = Path(out)
    vp, ss_noise, walk_rng, prior_rng = _plot_and_streams(
        plot_size, trees, seed, resolution, start_xy, forest_kwargs, scanner_kwargs
    )
    config = replace(
        config or ExplorationConfig(),
        strategy=strategy,
        plot=tuple(map(tuple, vp.plot_polygon().tolist())),
    )
    search = (
        {
            "xy_m": round(max(1.0, 4 * walk_sigma_m), 3),
            "z_m": 1.25,
            "heading_deg": round(min(180.0, max(15.0, 4 * compass_sigma_deg)), 3),
        }
        if use_prior
        else {}
    )
    writer = SurveyWriter(
        out, vp, search=search, rng_noise=np.random.default_rng(ss_noise), params=campaign_params
    )
    cache = SurfaceCache()
    say(
        f"explore: {trees} trees in a {plot_size:g} m plot (seed {seed}), budget {budget} "
        f"scans, {resolution} resolution"
    )

    rows: list[dict] = []
    sid = writer.add_scan(vp.origin)
    writer.write_manifest()
    say(f"scan {sid} (1/{budget}) at the start")
    pipeline_s = _run(out, say)
    t0 = time.perf_counter()
    sm = read_map(out, config, cache, current=sid, fallback_xy=(0.0, 0.0))
    plan_s = time.perf_counter() - t0
    found, with_dbh, _ = _tree_counts(out, sm.trees)
    cov = sm.plan.coverage["coverage"]
    rows.append(
        dict(
            step=0,
            scan=sid,
            reference="",
            planned_x=0.0,
            planned_y=0.0,
            true_x=0.0,
            true_y=0.0,
            true_heading_deg=0.0,
            expected_new_m2=np.nan,
            predicted_common_stems=np.nan,
            predicted_overlap=np.nan,
            path_m=0.0,
            registered=True,
            pose_error_m=0.0,
            heading_error_deg=0.0,
            coverage=cov,
            gain=cov,
            trees=found,
            trees_with_dbh=with_dbh,
            pipeline_seconds=pipeline_s,
            plan_seconds=plan_s,
        )
    )
    _save_plan(out, 0, sm, f"after scan {sid}")
    say(f"  coverage {100 * cov:.1f} %, {found} trees ({with_dbh} with DBH)")
    stop = "budget reached"
    for k in range(1, budget):
        props = sm.plan.proposals
        feasible = props[props["feasible"]] if len(props) else props
        if feasible.empty:
            stop = "no position keeps enough overlap to register"
            break
        best = feasible.iloc[0]
        if best.expected_gain_m2 < min_expected_m2:
            stop = f"no position is expected to add {min_expected_m2:g} m2"
            break
        planned = np.array([best.x, best.y])
        ref = str(best.reference_scan)
        ref_row = sm.scans[sm.scans["scan"] == ref].iloc[0]
        # walk there (planning error), set the tripod up facing away from the reference
        target_w = vp.to_world(planned)[0]
        actual_w = vp.free_near(
            target_w
            + np.clip(walk_rng.normal(0, walk_sigma_m, 2), -3 * walk_sigma_m, 3 * walk_sigma_m),
            walk_rng,
        )
        ref_w = vp.to_world([ref_row.x, ref_row.y])[0]
        bearing = np.degrees(np.arctan2(*(actual_w - ref_w)[::-1]))
        pose = vp.pose_at(actual_w, bearing + walk_rng.uniform(-20, 20), walk_rng)
        sid = writer.add_scan(pose)
        truth_g = vp.global_pose(pose)
        if use_prior:
            heading_prior = truth_g[3] + prior_rng.normal(0, compass_sigma_deg)
            gz = _ground_at(sm.plan.grid, planned)
            prior = _prior_pose(planned, gz, heading_prior)
            refs = [ref] + _more_references(sm, planned, ref, config, max_pairs - 1)
            for r in refs:
                rr = sm.scans[sm.scans["scan"] == r].iloc[0]
                writer.add_pair(
                    sid, r, relative_pose_tuple(prior, (rr.x, rr.y, rr.z, rr.heading_deg))
                )
        writer.write_manifest()
        say(
            f"scan {sid} ({k + 1}/{budget}) at ({planned[0]:.1f}, {planned[1]:.1f}): expected "
            f"+{best.expected_new_m2:.0f} m2, {int(best.common_stems)} common stems with {ref}, "
            f"walk {best.path_m:.1f} m"
        )
        pipeline_s = _run(out, say)
        t0 = time.perf_counter()
        sm = read_map(out, config, cache, current=sid, fallback_xy=planned)
        plan_s = time.perf_counter() - t0
        registered, exy, eh = _registration_check(out, sm.poses, sid)
        found, with_dbh, _ = _tree_counts(out, sm.trees)
        new_cov = sm.plan.coverage["coverage"]
        rows.append(
            dict(
                step=k,
                scan=sid,
                reference=ref,
                planned_x=planned[0],
                planned_y=planned[1],
                true_x=truth_g[0],
                true_y=truth_g[1],
                true_heading_deg=truth_g[3],
                expected_new_m2=best.expected_new_m2,
                predicted_common_stems=int(best.common_stems),
                predicted_overlap=best.overlap_share,
                path_m=best.path_m,
                registered=registered,
                pose_error_m=exy,
                heading_error_deg=eh,
                coverage=new_cov,
                gain=new_cov - cov,
                trees=found,
                trees_with_dbh=with_dbh,
                pipeline_seconds=pipeline_s,
                plan_seconds=plan_s,
            )
        )
        _save_plan(out, k, sm, f"after scan {sid}")
        say(
            f"  {'registered' if registered else 'NOT registered'}"
            f"{f' (error {exy:.3f} m, {eh:.2f} deg)' if registered else ''}; "
            f"coverage {100 * new_cov:.1f} % "
            f"(+{100 * (new_cov - cov):.1f}), {found} trees ({with_dbh} with DBH)"
        )
        gain, cov = new_cov - cov, new_cov
        if gain < min_gain:
            stop = f"coverage stopped improving (+{100 * gain:.2f} % < {100 * min_gain:g} %)"
            break
    steps = pd.DataFrame(rows, columns=STEP_COLUMNS)
    steps.to_csv(out / "explore" / "steps.csv", index=False, float_format="%.4f")
    from forestmap_assets.io.campaign import load_campaign
    from forestmap_assets.outputs.exports import write_exports

    write_exports(load_campaign(out), out / "outputs", **(export_kwargs or {}))
    found, with_dbh, rmse = _tree_counts(out, sm.trees)
    positions = np.array([[p.x, p.y] for p in writer.poses])
    say(
        f"explore: stopped after {len(steps)} scans ({stop}); coverage {100 * cov:.1f} %, "
        f"{found} trees "
        f"({with_dbh} with DBH), walked {steps['path_m'].sum():.0f} m"
    )
    return ExploreResult(
        out,
        steps,
        float(cov),
        stop,
        found,
        with_dbh,
        rmse,
        float(steps["path_m"].sum()),
        time.perf_counter() - t_start,
        positions,
    )


def relative_pose_tuple(scan_pose, reference_pose) -> tuple:
    from forestmap_assets.core.geometry import relative_pose as rel

    return rel(scan_pose, reference_pose)


def _ground_at(grid, xy) -> float:
    ix, iy, inside = grid.cell_of(xy[0], xy[1])
    if grid.ground_z is None or not inside:
        return float(np.nanmedian(grid.ground_z)) if grid.ground_z is not None else -1.5
    return float(grid.ground_z[ix, iy])


def _more_references(sm: SurveyMap, xy, first: str, config: ExplorationConfig, n: int) -> list[str]:
    """Up to ``n`` further registered scans predicted to share enough stems with position ``xy``."""
    from forestmap_assets.core.exploration import stem_visibility, visible_stems

    if n <= 0 or len(sm.scans) < 2 or not len(sm.stems):
        return []
    kw = stem_visibility(sm.plan.config) if sm.plan.config is not None else stem_visibility(config)
    vs = visible_stems(np.asarray(xy)[None], sm.stems, **kw)
    vscan = visible_stems(sm.scans[["x", "y"]].to_numpy(float), sm.stems, **kw)
    common = (vscan & vs).sum(axis=1)
    order = np.argsort(-common, kind="stable")
    ids = sm.scans["scan"].astype(str).to_numpy()
    return [ids[i] for i in order if ids[i] != first and common[i] >= config.min_common_stems][:n]


# ---- fixed positions (baselines) ------------------------------------------------------------
def grid_positions(n: int, plot_size: float) -> np.ndarray:
    """``n`` positions (world) of a regular grid over the plot (inferred baseline): ``k =
    ceil(sqrt(n))`` columns and ``ceil(n / k)`` rows, each position at the centre of its cell of
    the plot's partition (a short last row is spread over its own cells), serpentine order."""
    k = int(np.ceil(np.sqrt(n)))
    rows = int(np.ceil(n / k))
    ys = -plot_size / 2 + (np.arange(rows) + 0.5) * plot_size / rows
    pts = []
    for j, y in enumerate(ys):
        m = min(k, n - j * k)
        xs = -plot_size / 2 + (np.arange(m) + 0.5) * plot_size / m
        pts.extend((x, y) for x in (xs if j % 2 == 0 else xs[::-1]))
    return np.array(pts)


def random_positions(
    vp: VirtualPlot,
    n: int,
    rng: np.random.Generator,
    margin_m: float = 2.0,
    clearance_m: float = 0.5,
) -> np.ndarray:
    """``n`` random positions (world) inside the plot that one can stand at (clear of stems and
    understorey); the first is the survey's start."""
    h = vp.plot_size / 2 - margin_m
    out = [np.array([vp.origin.x, vp.origin.y])]
    while len(out) < n:
        cand = rng.uniform(-h, h, (64, 2))
        ok = vp.is_free(cand, clearance_m)
        out.extend(cand[ok][: n - len(out)])
    return np.array(out[:n])


def survey_positions(
    out,
    positions_world: np.ndarray,
    *,
    plot_size: float = 40.0,
    trees: int = 40,
    seed: int = 0,
    resolution: str = "full",
    config: ExplorationConfig | None = None,
    start_xy: Sequence[float] | None = None,
    walk_sigma_m: float = 0.3,
    compass_sigma_deg: float = 5.0,
    use_prior: bool = True,
    max_pairs: int = 2,
    pair_distance_m: float = 20.0,
    progress: Progress | None = None,
    forest_kwargs: dict | None = None,
    scanner_kwargs: dict | None = None,
    export_kwargs: dict | None = None,
    campaign_params: dict | None = None,
) -> ExploreResult:
    """Scan a fixed list of positions (world) of the same virtual plot as :func:`explore` with the
    same ``seed`` (the first position replaces the start), then run the pipeline once. Each scan is
    paired with its ``max_pairs`` nearest earlier positions within ``pair_distance_m``."""
    say = progress or (lambda _m: None)
    t_start = time.perf_counter()
    out = Path(out)
    vp, ss_noise, walk_rng, prior_rng = _plot_and_streams(
        plot_size, trees, seed, resolution, start_xy, forest_kwargs, scanner_kwargs
    )
    config = replace(
        config or ExplorationConfig(), plot=tuple(map(tuple, vp.plot_polygon().tolist()))
    )
    search = (
        {
            "xy_m": round(max(1.0, 4 * walk_sigma_m), 3),
            "z_m": 1.25,
            "heading_deg": round(min(180.0, max(15.0, 4 * compass_sigma_deg)), 3),
        }
        if use_prior
        else {}
    )
    positions_world = np.asarray(positions_world, dtype=np.float64).reshape(-1, 2)
    first = vp.free_near(positions_world[0], walk_rng)
    vp.origin = vp.pose_at(first, vp.origin.heading_deg, walk_rng)
    writer = SurveyWriter(
        out, vp, search=search, rng_noise=np.random.default_rng(ss_noise), params=campaign_params
    )
    planned_g = vp.to_global(positions_world)
    priors: list[tuple] = []
    for k, p in enumerate(positions_world):
        if k == 0:
            pose = vp.origin
        else:
            actual = vp.free_near(
                p
                + np.clip(walk_rng.normal(0, walk_sigma_m, 2), -3 * walk_sigma_m, 3 * walk_sigma_m),
                walk_rng,
            )
            pose = vp.pose_at(actual, walk_rng.uniform(-180, 180), walk_rng)
        sid = writer.add_scan(pose)
        g = vp.global_pose(pose)
        heading_prior = g[3] + (prior_rng.normal(0, compass_sigma_deg) if k else 0.0)
        priors.append(
            (planned_g[k, 0], planned_g[k, 1], 0.0, heading_prior) if k else (0.0, 0.0, 0.0, 0.0)
        )
        if use_prior and k:
            d = np.hypot(*(planned_g[:k] - planned_g[k]).T)
            for j in [j for j in np.argsort(d, kind="stable") if d[j] <= pair_distance_m][
                :max_pairs
            ]:
                writer.add_pair(sid, writer.ids[j], relative_pose_tuple(priors[k], priors[j]))
        say(f"scan {sid} ({k + 1}/{len(positions_world)}) at world ({p[0]:.1f}, {p[1]:.1f})")
    writer.write_manifest()
    pipeline_s = _run(out, say)
    cache = SurfaceCache()
    sm = read_map(out, config, cache)
    rows = []
    for k, sid in enumerate(writer.ids):
        registered, exy, eh = _registration_check(out, sm.poses, sid) if k else (True, 0.0, 0.0)
        g = vp.global_pose(writer.poses[k])
        rows.append(
            dict(
                step=k,
                scan=sid,
                reference="",
                planned_x=planned_g[k, 0],
                planned_y=planned_g[k, 1],
                true_x=g[0],
                true_y=g[1],
                true_heading_deg=g[3],
                expected_new_m2=np.nan,
                predicted_common_stems=np.nan,
                predicted_overlap=np.nan,
                path_m=float(np.hypot(*(planned_g[k] - planned_g[k - 1]))) if k else 0.0,
                registered=registered,
                pose_error_m=exy,
                heading_error_deg=eh,
                coverage=np.nan,
                gain=np.nan,
                trees=np.nan,
                trees_with_dbh=np.nan,
                pipeline_seconds=pipeline_s if k == 0 else 0.0,
                plan_seconds=0.0,
            )
        )
    steps = pd.DataFrame(rows, columns=STEP_COLUMNS)
    cov = sm.plan.coverage["coverage"]
    steps.loc[steps.index[-1], "coverage"] = cov
    steps.to_csv(out / "explore" / "steps.csv", index=False, float_format="%.4f")
    _save_plan(out, len(steps) - 1, sm, f"fixed positions, after scan {writer.ids[-1]}")
    from forestmap_assets.io.campaign import load_campaign
    from forestmap_assets.outputs.exports import write_exports

    write_exports(load_campaign(out), out / "outputs", **(export_kwargs or {}))
    found, with_dbh, rmse = _tree_counts(out, sm.trees)
    return ExploreResult(
        out,
        steps,
        float(cov),
        "fixed positions",
        found,
        with_dbh,
        rmse,
        float(steps["path_m"].sum()),
        time.perf_counter() - t_start,
        np.array([[p.x, p.y] for p in writer.poses]),
    )
