"""``report.html``: one self-contained page per campaign (DESIGN.md section 4).

Everything is inline (CSS, PNG images as data URIs), so the file can be mailed or archived
alone. Sections: summary numbers, the map picture (``map.png``) and the elevation map, the
registration network, poses with sigmas, registrations with their status, residual verdicts,
the tree list summary with a DBH histogram, the accuracy against the truth of a simulated
campaign (when ``truth/`` exists), timings per stage, and the resolved parameters.

Timings (seconds per stage) are given by the caller
(:func:`forestmap_assets.orchestration.timings.stage_timings` reads them from the Dagster
instance); the registrations table adds each pair's search time.
"""

from __future__ import annotations

import base64
import html
import json
import os
from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from forestmap_assets.access import load_asset
from forestmap_assets.io.campaign import Campaign

CSS = """
body{font-family:-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:1.5em auto;
max-width:1250px;
color:#222;padding:0 1em}
h1{margin-bottom:.1em}h2{border-bottom:2px solid #ddd;padding-bottom:.2em;margin-top:1.6em}
.sub{color:#666;margin-top:0}
.cards{display:flex;flex-wrap:wrap;gap:.6em}
.card{border:1px solid #ddd;border-radius:6px;padding:.5em .9em;min-width:9em;background:#fafafa}
.card .v{font-size:1.5em;font-weight:600}.card .k{color:#666;font-size:.85em}
.card.bad{border-color:#c51b1b;background:#fdf0f0}.card.good{border-color:#1b7837;background:#f0f8f2}
table{border-collapse:collapse;font-size:.85em;margin:.4em 0}
th,td{border:1px solid #ddd;padding:.2em .5em;text-align:right}th{background:#f3f3f3}
td.t{text-align:left}
.accepted,.ok,.admitted{color:#1b7837;font-weight:600}.rejected{color:#d95f02;font-weight:600}
.failed,.inconsistent{color:#c51b1b;font-weight:600}
img{max-width:100%;border:1px solid #eee}
.row{display:flex;flex-wrap:wrap;gap:1em;align-items:flex-start}.row>div{flex:1 1 480px}
details{margin:.5em 0}pre{background:#f7f7f7;padding:.6em;overflow:auto;font-size:.8em}
.note{color:#666;font-size:.85em}
"""


# ------------------------------------------------------------------------------------------
# data




def _load(name: str, campaign: Campaign, stored: Mapping[str, Any] | None = None):
    if stored is not None and name in stored:
        return stored[name]
    try:
        return load_asset(name, campaign=campaign)
    except FileNotFoundError:
        return None


def _truth_accuracy(campaign: Campaign, out_dir: Path):
    if (
        not (campaign.root / "truth" / "poses.csv").is_file()
        or not (out_dir / "poses.csv").is_file()
    ):
        return None
    from forestmap_assets.sim.evaluate import evaluate_campaign

    try:
        return evaluate_campaign(campaign.root, out_dir)
    except (OSError, KeyError, ValueError):
        return None


# ------------------------------------------------------------------------------------------
# html pieces


def _img(data: bytes, alt: str) -> str:
    b64 = base64.b64encode(data).decode()
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{b64}">'


PIECES = "report pieces"  # the key of the drawn pieces in a ``stored`` dict


def _piece(stored, name: str, make):
    """A drawn piece of the report (a figure's ``<img>``, the truth comparison) kept in
    ``stored[PIECES]`` when ``stored`` is a dict, so that the report built again from the same
    assets after :func:`draw_report_pieces` does not draw it twice."""
    pieces = stored.setdefault(PIECES, {}) if isinstance(stored, dict) else {}
    if name not in pieces:
        pieces[name] = make()
    return pieces[name]


def draw_report_pieces(campaign: Campaign, out_dir: str | Path, stored: dict) -> None:
    """Draw the report's figures and truth comparison into ``stored`` (the assets the map's
    files read) while the where-to-scan-next stages still run (issue 16): the report written
    after them only adds their section and the timings."""
    build_report(campaign, out_dir, stored=stored)


def _fig(fig, alt: str) -> str:
    from forestmap_assets.outputs.figures.common import png_bytes

    return _img(png_bytes(fig, dpi=100), alt)


def _fmt(v, digits: int) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return ""
    if isinstance(v, (bool, np.bool_)):
        return "true" if v else "false"
    if isinstance(v, (float, np.floating)):
        return f"{v:.{digits}f}"
    return html.escape(str(v))


def html_table(
    df: pd.DataFrame,
    digits: dict[str, int] | None = None,
    classed: tuple[str, ...] = ("status", "verdict"),
    default_digits: int = 3,
) -> str:
    """A plain HTML table; numbers right-aligned with ``digits`` per column, text left, cells of
    ``classed`` columns carry their value as CSS class (status colours)."""
    digits = digits or {}
    if df is None or len(df) == 0:
        return '<p class="note">(none)</p>'
    head = "".join(f"<th>{html.escape(str(c))}</th>" for c in df.columns)
    body = []
    for row in df.itertuples(index=False):
        cells = []
        for col, v in zip(df.columns, row, strict=True):
            text = _fmt(v, digits.get(col, default_digits))
            cls = []
            if not isinstance(v, (int, float, np.number)) or isinstance(v, (bool, np.bool_)):
                cls.append("t")
            if col in classed and isinstance(v, str):
                cls.append(html.escape(v))
            attr = f' class="{" ".join(cls)}"' if cls else ""
            cells.append(f"<td{attr}>{text}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>"


def _card(value, label: str, state: str = "") -> str:
    return (
        f'<div class="card {state}"><div class="v">{html.escape(str(value))}</div>'
        f'<div class="k">{html.escape(label)}</div></div>'
    )


# ------------------------------------------------------------------------------------------
# the page


def build_report(
    campaign: Campaign, out_dir: str | Path, *, timings: pd.DataFrame | None = None,
    stored: Mapping[str, Any] | None = None,
) -> str:
    """The HTML text of ``report.html`` for a materialised campaign (see the module docstring).

    Pictures already written to ``out_dir`` (``map.png``, ``elevation.png``) are embedded;
    the network, residual and DBH figures are drawn here. ``stored``: assets already read from
    the store, by name (the exports pass theirs; the others are read here)."""
    from forestmap_assets.core.features.elevation import elevation_from_table
    from forestmap_assets.outputs.figures.elevation import elevation_figure
    from forestmap_assets.outputs.figures.mapping import (
        dbh_histogram,
        network_figure,
        residual_figure,
    )

    out_dir = Path(out_dir)
    omap = _load("optimal_map", campaign, stored) or {}
    regs_bundle = _load("refined_registrations", campaign, stored) or {}
    residuals = _load("residual_checks", campaign, stored)
    trees = _load("tree_list", campaign, stored)
    integrated = _load("integrated_map", campaign, stored) or {}
    poses = omap.get("poses")
    links = omap.get("links")
    regs = regs_bundle.get("registrations")
    mp = campaign.params.mapping
    if timings is None:
        timings = pd.DataFrame({"stage": ["timings unavailable: no run history given"]})

    n_scans = len(campaign.scans)
    n_reg = int(poses["registered"].astype(bool).sum()) if poses is not None else 0
    counts = regs["status"].value_counts().to_dict() if regs is not None and len(regs) else {}
    admitted = (
        int((links["status"] == "admitted").sum())
        if links is not None and len(links) and "status" in links
        else 0
    )
    bad = (
        int((residuals["verdict"] != "ok").sum()) if residuals is not None and len(residuals) else 0
    )
    n_res = len(residuals) if residuals is not None else 0
    n_trees = len(trees) if trees is not None else 0
    dbh = trees["dbh_m"].dropna() if trees is not None and len(trees) else pd.Series(dtype=float)
    n_cyl = len(integrated["cylinders"]) if "cylinders" in integrated else 0
    total_s = float(np.nansum(timings["seconds"])) if "seconds" in timings else np.nan

    parts: list[str] = []
    add = parts.append
    add(f"<h1>{html.escape(campaign.name)}</h1>")
    add(
        f'<p class="sub">campaign folder <code>{html.escape(str(campaign.root))}</code>, '
        f"environment <b>{html.escape(campaign.environment)}</b>, "
        f"frame of scan <b>{html.escape(campaign.scan_ids[0])}</b>; "
        f"report written {datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC')}</p>"
    )

    add("<h2>Summary</h2><div class='cards'>")
    add(_card(f"{n_reg}/{n_scans}", "scans registered", "good" if n_reg == n_scans else "bad"))
    add(
        _card(
            f"{counts.get('accepted', 0)}/{counts.get('rejected', 0)}/{counts.get('failed', 0)}",
            "pairs accepted / rejected / failed",
        )
    )
    add(_card(admitted, "links in the optimal map"))
    add(_card(f"{n_res - bad}/{n_res}", "residual checks ok", "good" if bad == 0 else "bad"))
    add(_card(n_trees, "trees"))
    add(_card(f"{100 * dbh.median():.1f} cm" if len(dbh) else "-", "median DBH"))
    add(_card(n_cyl, "cylinder segments"))
    add(_card(f"{total_s:.0f} s" if np.isfinite(total_s) else "-", "processing time (stages)"))
    add("</div>")

    accuracy = _piece(stored, "accuracy", lambda: _truth_accuracy(campaign, out_dir))
    if accuracy is not None:
        s = accuracy.summary()
        add("<h2>Against the simulator's truth</h2><div class='cards'>")
        add(_card(f"{100 * s['max_xy_error_m']:.1f} cm", "largest xy pose error"))
        add(_card(f"{s['max_heading_error_deg']:.2f} deg", "largest heading error"))
        add(_card(f"{100 * s['detection_rate']:.0f} %", "trees found (seen from 2+ scans)"))
        add(_card(f"{100 * s['dbh_rmse_m']:.1f} cm", "DBH RMSE"))
        add(_card(f"{100 * s['dbh_bias_m']:+.1f} cm", "DBH bias"))
        add(_card(s["false_trees"], "trees not in the truth"))
        add("</div>")
        add(
            '<p class="note">Pose errors (m, deg) against <code>truth/poses.csv</code>; '
            "<code>n*</code>: error divided by the reported standard deviation.</p>"
        )
        add(html_table(accuracy.poses, {c: 3 for c in accuracy.poses.columns}))

    add("<h2>Map</h2>")
    map_png = out_dir / "map.png"
    if map_png.is_file():
        add(_img(map_png.read_bytes(), "3-D map: cylinders, ground and scan positions"))
        add(
            '<p class="note">Cylinder segments of every scan (brown) on the 0.6 m ground model '
            "(mean of the 5 lowest 0.1 m cells), scan frames x red, y green, z blue "
            "(JP Figs. 12-13).</p>"
        )
    add("<div class='row'>")
    elev_png = out_dir / "elevation.png"
    if elev_png.is_file():
        add(f"<div>{_img(elev_png.read_bytes(), 'merged elevation map')}</div>")
    elif "elevation" in integrated and poses is not None:
        grid = elevation_from_table(integrated["elevation"])
        add(f"<div>{_piece(stored, 'elevation', lambda: _fig(elevation_figure(grid, poses, trees), 'merged elevation map'))}</div>")
    if poses is not None:
        add(f"<div>{_piece(stored, 'network', lambda: _fig(network_figure(poses, regs, links), 'registration network'))}</div>")
    add("</div>")

    add("<h2>Poses</h2>")
    add(
        f'<p class="note">Global poses in the levelled frame of scan '
        f"{html.escape(campaign.scan_ids[0])} with their standard deviations from the optimal map "
        "(thesis 3.2.2, 6.4).</p>"
    )
    add(html_table(poses, {"heading_deg": 3, "sd_heading_deg": 3}))
    levelled = [e for e in campaign.scans if e.levelled_from is not None]
    if levelled:  # tilts estimated from the stems (core/mapping/levelling.py, levelling.yaml)
        add(f'<p class="note">{len(levelled)} scan{"s" if len(levelled) > 1 else ""} levelled by the tilt '
            "estimated from the stems they share (levelling.yaml; roll, pitch in deg, sd): "
            + ", ".join(f"{html.escape(e.id)} {e.tilt_deg[0]:.3f} / {e.tilt_deg[1]:.3f} ({e.tilt_sd_deg:.3f})"
                        for e in levelled) + ".</p>")

    add("<h2>Registrations</h2>")
    if regs is not None:
        cols = [
            c
            for c in (
                "scan",
                "reference",
                "dx",
                "dy",
                "dz",
                "dheading_deg",
                "sd_x",
                "sd_y",
                "sd_z",
                "sd_heading_deg",
                "log_score",
                "n_points",
                "matched_points",
                "seconds",
                "status",
                "reason",
                "refine_method",
                "refined",
            )
            if c in regs
        ]
        add(
            '<p class="note">Branch-and-bound results (thesis 5.3.3); an accepted pair is refined on '
            "the raw points (refine_method: HICP with colour, else point-to-plane ICP, Men 2012 "
            "ch. 5) and its refined pose and sigmas are used (refined = true) when they fit the "
            "points better.</p>"
        )
        add(html_table(regs[cols], {"log_score": 1, "seconds": 2, "matched_points": 0}))
    refinements = regs_bundle.get("refinements")
    if refinements is not None and len(refinements):
        add("<details><summary>refinement of each accepted pair</summary>")
        add(html_table(refinements[[c for c in ("scan", "reference", "method", "used", "reason", "fit_bnb_m",
                                                 "fit_refined_m", "iterations", "seconds") if c in refinements]],
                       {"fit_bnb_m": 4, "fit_refined_m": 4, "seconds": 1}))
        add("</details>")
    if links is not None and len(links) and "status" in links:
        add("<details><summary>how each link entered the optimal map</summary>")
        add(
            html_table(
                links[
                    [
                        c
                        for c in ("step", "scan", "reference", "role", "status", "reason")
                        if c in links
                    ]
                ]
            )
        )
        add("</details>")

    add("<h2>Residual checks</h2>")
    add(
        '<p class="note">Residuals of eq. (11) of every admitted observation, divided by its '
        f"sigma; a link is inconsistent beyond {mp.residual_sigmas:g} sigma in x, y or heading, "
        f"or {mp.z_residual_sigmas:g} sigma in z (thesis 6.4, 7.1).</p>"
    )
    if residuals is not None and len(residuals):
        add(
            html_table(
                residuals,
                {c: 3 for c in ("ex", "ey", "ez", "eheading_deg")}
                | {c: 2 for c in ("rx", "ry", "rz", "rheading")},
            )
        )
        add(_piece(stored, "residuals", lambda: _fig(
            residual_figure(residuals, mp.residual_sigmas, mp.z_residual_sigmas), "residuals")))
    else:
        add('<p class="note">(no admitted observation)</p>')

    add("<h2>Trees</h2>")
    if trees is not None and len(trees):
        two = int((trees["n_scans"] >= 2).sum())
        add("<div class='cards'>")
        add(_card(n_trees, "trees"))
        add(_card(len(dbh), "with a DBH"))
        add(_card(two, "seen from 2 or more scans"))
        if len(dbh):
            add(_card(f"{100 * dbh.mean():.1f} cm", "mean DBH"))
            add(_card(f"{100 * dbh.min():.1f}-{100 * dbh.max():.1f} cm", "DBH range"))
        add("</div><div class='row'><div>")
        truth = None
        truth_csv = campaign.root / "truth" / "trees.csv"
        if truth_csv.is_file():
            truth = pd.read_csv(truth_csv)
        add(_piece(stored, "dbh", lambda: _fig(dbh_histogram(trees, truth), "DBH histogram")))
        add("</div><div>")
        add("<details><summary>the tree list</summary>")
        add(html_table(trees, {"dbh_m": 3, "visible_length_m": 2}))
        add("</details></div></div>")
    else:
        add('<p class="note">(no tree)</p>')

    vantage = _load("next_vantage_points", campaign, stored)
    if vantage is not None and len(vantage.get("coverage", [])):
        cov = vantage["coverage"].iloc[0]
        props = vantage["proposals"]
        add("<h2>Where to scan next</h2>")
        add('<p class="note">Exploration grid of the plot (Men 2012 ch. 3, 6): cells mapped as '
            "ground or obstacle relative to the local ground, frontier cells, and candidate "
            "positions reachable on foot, ranked by the new area a 2-D visibility model with trunk "
            "occlusion expects, keeping enough common stems to register, and by walking distance."
            "</p><div class='cards'>")
        add(_card(f"{100 * cov['coverage']:.1f} %", "of the plot mapped"))
        add(_card(f"{cov['mapped_area_m2']:.0f} m²", "mapped area"))
        add(_card(f"{cov['median_points_per_m2']:.0f}", "median points per m²"))
        add(_card(int(props["feasible"].sum()) if len(props) else 0, "feasible positions"))
        add("</div><div class='row'><div>")
        if "picture" in vantage and len(vantage["picture"]):  # drawn by next_vantage_points
            add(_img(bytes(vantage["picture"]["png"].iloc[0]), "next vantage positions"))
        add("</div><div>")
        cols = ["rank", "x", "y", "expected_new_m2", "common_stems", "reference_scan", "path_m", "feasible"]
        add(html_table(props[[c for c in cols if c in props]].head(10),
                       {"x": 1, "y": 1, "expected_new_m2": 1, "path_m": 1}))
        add("</div></div>")

    add("<h2>Timings</h2>")
    add(
        '<p class="note">Seconds of the Dagster steps that produced the current outputs of each '
        "stage (per-scan stages: summed over the scans), and the CPU seconds of their own "
        "threads (where far fewer, the steps waited for a core that others held; Open3D's "
        "threads are not counted); cached stages keep the time of the run that made them.</p>"
    )
    add(html_table(timings, {"seconds": 1, "cpu_seconds": 1, "slowest_seconds": 1}))

    add("<h2>Parameters</h2><details><summary>resolved parameters of every stage</summary><pre>")
    add(html.escape(json.dumps(campaign.params.model_dump(), indent=1, default=str)))
    add("</pre></details>")

    return (
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
        f"<title>forestmap report: {html.escape(campaign.name)}</title>"
        f"<style>{CSS}</style></head><body>" + "\n".join(parts) + "</body></html>"
    )


def write_report(
    campaign: Campaign, out_dir: str | Path, *, timings: pd.DataFrame | None = None,
    stored: Mapping[str, Any] | None = None,
) -> Path:
    """Write ``out_dir/report.html`` atomically; return its path (``stored``: see
    :func:`build_report`)."""
    out_dir = Path(out_dir)
    text = build_report(campaign, out_dir, timings=timings, stored=stored)
    path = out_dir / "report.html"
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    out_dir.mkdir(parents=True, exist_ok=True)
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path
