"""Coarse registration without any prior in the Fourier domain, H-EGI pipeline (men spec 4.1, 4.5,
10; checklist 8-12): hue filter, crop, voxel sub-sampling, outlier filter and PCA normals, rotation
by EGI correlation (top_k peaks, each verified by its translation-correlation peak), translation by
occupancy-grid correlation, Eq. 4.9 error."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from forestmap_assets.core.cloud import pca_normals, radius_outlier_mask, voxel_subsample
from forestmap_assets.core.registration.fourier_rotation import (
    egi,
    euler_zyz,
    heading_correlation,
    heading_peaks,
    peak_rotation,
    sh_coefficients,
    so3_correlation,
    so3_peaks,
)
from forestmap_assets.core.registration.fourier_translation import translation_by_correlation


@dataclass
class CoarseResult:
    """Outcome of :func:`coarse_register`: ``model ~ R data + T``; ``candidates`` one row per
    verified rotation peak (rotation score, translation score, translation)."""

    rotation: np.ndarray
    translation: np.ndarray
    score: float
    seconds: float
    n_model: int
    n_data: int
    mode: str
    candidates: pd.DataFrame = field(default_factory=pd.DataFrame)
    error: float = np.nan

    @property
    def pose4(self) -> np.ndarray:
        r, t = self.rotation, self.translation
        return np.array([t[0], t[1], t[2], np.degrees(np.arctan2(r[1, 0], r[0, 0]))])


def prepare_cloud(
    xyz: np.ndarray,
    hue=None,
    *,
    hue_max: float | None = None,
    voxel_m: float = 0.1,
    outlier_radius_m: float | None = 0.3,
    outlier_min_neighbours: int = 3,
    normal_k: int = 20,
    origin=(0.0, 0.0, 0.0),
    max_range_m: float | None = None,
    z_band_m: tuple[float, float] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Steps 3-5 of spec 4.1 on one cloud: hue filter (``h <= hue_max``), crop to
    ``max_range_m`` horizontally and to the height band ``z_band_m`` around ``origin`` (forest,
    inferred), voxel sub-sampling, radius outlier filter, PCA normals toward ``origin``."""
    p = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    keep = np.isfinite(p).all(axis=1)
    if hue_max is not None and hue is not None:
        keep &= np.asarray(hue, dtype=np.float64).reshape(-1) <= hue_max
    if max_range_m is not None:
        keep &= np.linalg.norm(p[:, :2] - np.asarray(origin)[:2], axis=1) <= max_range_m
    if z_band_m is not None:
        dz = p[:, 2] - float(origin[2])
        keep &= (dz >= z_band_m[0]) & (dz <= z_band_m[1])
    p = p[keep]
    p = p[voxel_subsample(p, voxel_m)] if voxel_m else p
    if outlier_radius_m:
        p = p[radius_outlier_mask(p, outlier_radius_m, outlier_min_neighbours)]
    n, _ = pca_normals(p, normal_k, origin)
    ok = np.isfinite(n).all(axis=1)
    return p[ok], n[ok]


def registration_error(model_points: np.ndarray, moved_data: np.ndarray, r_l: float) -> float:
    """Eq. 4.9: mean distance of data points to their nearest model point over pairs closer
    than ``r_l`` (NaN without pairs)."""
    d, _ = cKDTree(np.asarray(model_points)).query(np.asarray(moved_data), distance_upper_bound=r_l)
    d = d[np.isfinite(d)]
    return float(d.mean()) if len(d) else np.nan


def coarse_register(
    model_xyz: np.ndarray,
    data_xyz: np.ndarray,
    model_hue=None,
    data_hue=None,
    *,
    mode: str = "heading",
    rotation: str = "egi",
    bandwidth: int = 32,
    top_k: int = 4,
    hue_max: float | None = None,
    voxel_m: float = 0.1,
    normal_k: int = 20,
    cell_m: float = 0.2,
    scan_cell_m: float = 0.4,
    ground_weight: float = 0.05,
    ground_normal_z: float = 0.9,
    max_range_m: float | None = None,
    z_band_m: tuple[float, float] | None = None,
    n_heading: int = 720,
    error_radius_m: float = 0.5,
    max_cells: int = 8_000_000,
    prepared=None,
) -> CoarseResult:
    """Coarse registration without a prior (spec 4.1): data onto model, both in their scanner
    frames (origin at the sensor).

    ``mode`` 'so3' (full rotation, SOFT correlation of the EGIs) or 'heading' (levelled scans:
    rotation about z only). ``rotation`` 'egi' (the thesis: rotation from the EGI correlation,
    its ``top_k`` peaks verified by the translation correlation, spec 10) or, for ``mode=
    'heading'`` only, 'occupancy_scan' (forest adaptation, inferred: the translation correlation
    itself is evaluated for ``2L`` headings at ``scan_cell_m``, the ``top_k`` best headings are
    refined on a 4x finer heading grid, the winner's translation is solved at ``cell_m``).
    ``hue_max`` applies the hue low-pass filter (spec 4.5; skipped without hue). ``max_range_m``
    and ``z_band_m`` crop each cloud around its sensor (:func:`prepare_cloud`). ``prepared`` =
    ((model points, normals), (data points, normals)) skips :func:`prepare_cloud`.
    """
    if mode not in ("so3", "heading"):
        raise ValueError(f"mode: expected 'so3' or 'heading', got {mode!r}")
    if rotation not in ("egi", "occupancy_scan") or (
        rotation == "occupancy_scan" and mode != "heading"
    ):
        raise ValueError(
            f"rotation: expected 'egi' or (heading mode) 'occupancy_scan', got {rotation!r}"
        )
    t0 = time.perf_counter()
    if prepared is None:
        kw = dict(
            hue_max=hue_max,
            voxel_m=voxel_m,
            normal_k=normal_k,
            max_range_m=max_range_m,
            z_band_m=z_band_m,
        )
        pm, nm = prepare_cloud(model_xyz, model_hue, **kw)
        pdt, nd = prepare_cloud(data_xyz, data_hue, **kw)
    else:
        (pm, nm), (pdt, nd) = prepared
    if len(pm) < 10 or len(pdt) < 10:
        return CoarseResult(
            np.eye(3), np.zeros(3), np.nan, time.perf_counter() - t0, len(pm), len(pdt), mode
        )
    wm = np.where(np.abs(nm[:, 2]) >= ground_normal_z, ground_weight, 1.0)
    wd = np.where(np.abs(nd[:, 2]) >= ground_normal_z, ground_weight, 1.0)

    bounds, cache = None, {}
    if mode == "heading":  # one grid box for every heading: the model's FFT is computed once
        reach = float(np.hypot(pdt[:, 0], pdt[:, 1]).max())
        lo = np.minimum(pm.min(axis=0), [-reach, -reach, pdt[:, 2].min()])
        hi = np.maximum(pm.max(axis=0), [reach, reach, pdt[:, 2].max()])
        bounds = (lo, hi)

    def translate(r, cell):
        return translation_by_correlation(
            pm,
            pdt @ r.T,
            cell,
            model_weights=wm,
            data_weights=wd,
            max_cells=max_cells,
            bounds=bounds,
            cache=cache,
        )

    rows = []
    if rotation == "egi":
        fm = sh_coefficients(egi(nm, bandwidth), bandwidth)
        fd = sh_coefficients(egi(nd, bandwidth), bandwidth)
        if mode == "so3":
            peaks = so3_peaks(so3_correlation(fm, fd, bandwidth), bandwidth, top_k=top_k)
            rots = [peak_rotation(r) for _, r in peaks.iterrows()]
        else:
            heads, g = heading_correlation(fm, fd, bandwidth, n_heading)
            peaks = heading_peaks(heads, g, top_k=top_k)
            rots = [euler_zyz(np.radians(h), 0.0, 0.0) for h in peaks["heading_deg"]]
        for i, r in enumerate(rots):
            t, score, info = translate(r, cell_m)
            rows.append(
                {
                    "rank": i,
                    "rotation_score": float(peaks["score"].iloc[i]),
                    "translation_score": score,
                    "heading_deg": float(np.degrees(np.arctan2(r[1, 0], r[0, 0]))),
                    "tx": t[0],
                    "ty": t[1],
                    "tz": t[2],
                    "cell_m": info["cell_m"],
                }
            )
    else:
        step = 360.0 / (2 * bandwidth)
        coarse = []
        for h in np.arange(2 * bandwidth) * step - 180.0:
            _, score, _ = translate(euler_zyz(np.radians(h), 0.0, 0.0), scan_cell_m)
            coarse.append((h, score))
        coarse = pd.DataFrame(coarse, columns=["heading_deg", "score"])
        best_h = []
        for h in coarse.sort_values("score", ascending=False)["heading_deg"]:
            if all(abs((h - b + 180.0) % 360.0 - 180.0) > 1.5 * step for b in best_h):
                best_h.append(h)
            if len(best_h) >= top_k:
                break
        fine = []
        for h0 in best_h:  # the best of a 4x finer heading grid around each coarse peak
            local = []
            for h in h0 + np.linspace(-step, step, 9):
                _, score, _ = translate(euler_zyz(np.radians(h), 0.0, 0.0), scan_cell_m)
                local.append((float((h + 180.0) % 360.0 - 180.0), score))
            fine.append(max(local, key=lambda v: v[1]))
        for i, (h, sc) in enumerate(fine):
            r = euler_zyz(np.radians(h), 0.0, 0.0)
            t, score, info = translate(r, cell_m)
            rows.append(
                {
                    "rank": i,
                    "rotation_score": sc,
                    "translation_score": score,
                    "heading_deg": h,
                    "tx": t[0],
                    "ty": t[1],
                    "tz": t[2],
                    "cell_m": info["cell_m"],
                }
            )
    cands = pd.DataFrame(rows)
    best = cands.iloc[int(np.argmax(cands["translation_score"].to_numpy()))] if len(cands) else None
    if best is None:
        return CoarseResult(
            np.eye(3), np.zeros(3), np.nan, time.perf_counter() - t0, len(pm), len(pdt), mode, cands
        )
    if mode == "so3":
        r = rots[int(best["rank"])]
    else:
        r = euler_zyz(np.radians(best["heading_deg"]), 0.0, 0.0)
    t = best[["tx", "ty", "tz"]].to_numpy(float)
    err = registration_error(pm, pdt @ r.T + t, error_radius_m)
    return CoarseResult(
        r,
        t,
        float(best["translation_score"]),
        time.perf_counter() - t0,
        len(pm),
        len(pdt),
        mode,
        cands,
        err,
    )


def coarse_candidates(
    candidates: pd.DataFrame,
    clouds: dict[str, np.ndarray],
    *,
    search=(5.0, 1.25, 60.0),
    progress=None,
    **coarse_kw,
) -> pd.DataFrame:
    """Candidate pairs with every no-prior row (``source == 'no_prior'``) centred on its Fourier
    coarse registration (levelled scans: ``mode='heading'``) and narrowed to the ``search`` box
    (xy_m, z_m, heading_deg), ``source = 'fourier'``; the branch and bound then searches that box
    as it would around an a priori alignment (men spec 4.4: the coarse result is the initial
    guess of the fine stage). ``clouds`` maps scan ids to levelled points; ``coarse_kw`` go to
    :func:`coarse_register` (default ``rotation='occupancy_scan'``, inferred from the forest
    benchmark). Rows whose scans are missing are left unchanged."""
    out = candidates.copy()
    kw = {
        "mode": "heading",
        "rotation": "occupancy_scan",
        "max_range_m": 25.0,
        "z_band_m": (-4.0, 2.0),
    }
    kw.update(coarse_kw)
    prepared: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    prep_keys = ("hue_max", "voxel_m", "normal_k", "max_range_m", "z_band_m")

    def prep(sid):
        if sid not in prepared:
            prepared[sid] = prepare_cloud(clouds[sid], **{k: kw[k] for k in prep_keys if k in kw})
        return prepared[sid]

    run_kw = {k: v for k, v in kw.items() if k not in prep_keys}
    for i in out.index[out["source"] == "no_prior"]:
        scan, ref = out.at[i, "scan"], out.at[i, "reference"]
        if scan not in clouds or ref not in clouds:
            continue
        res = coarse_register(None, None, prepared=(prep(ref), prep(scan)), **run_kw)
        if not np.isfinite(res.score):
            continue
        x, y, z, h = res.pose4
        out.loc[i, ["cx", "cy", "cz", "cheading_deg"]] = [x, y, z, (h + 180.0) % 360.0 - 180.0]
        out.loc[i, ["hx", "hy", "hz", "hheading_deg"]] = [
            search[0],
            search[0],
            search[1],
            search[2],
        ]
        out.at[i, "source"] = "fourier"
        if progress:
            progress(
                f"fourier {scan}-{ref}: ({x:.2f}, {y:.2f}, {z:.2f}, {h:.1f} deg) in {res.seconds:.1f} s"
            )
    return out
