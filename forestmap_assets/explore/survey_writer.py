"""The growing campaign folder of a virtual survey (men_spec 7.7): ``OUT/scans/<id>.npz`` and
``OUT/campaign.yaml`` (scans, pairs with their a priori alignment, search box, params), and the
truth in the frame of the first scan (``OUT/truth/poses.csv``, ``trees.csv``, ``stems.csv``,
``plot.csv``, as ``simulate`` writes them)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from forestmap_assets.explore.virtual_plot import VirtualPlot
from forestmap_assets.sim.campaign import save_npz, scan_ids, visible_trees
from forestmap_assets.sim.scanner import ScanPose
from forestmap_assets.sim.stems import breast_height_table, stems_in_frame


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
            "sensor": {"angular_step_deg": [round(float(sc.d_az), 9), round(float(sc.d_el), 9)], **sc.sensor_beam()},
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
