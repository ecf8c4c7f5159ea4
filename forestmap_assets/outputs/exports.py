"""The files ``forestmap run`` writes (DESIGN.md section 4), read from the asset store.

Beyond the CSVs of section 4: ``elevation.png``
(:func:`~forestmap_assets.outputs.figures.elevation.elevation_figure`),
``map.png`` (:func:`~forestmap_assets.outputs.render.render_map`), ``report.html``
(:mod:`~forestmap_assets.report`), the registered point cloud of the campaign as ``cloud.laz``
and ``cloud.ply`` (thinned to ``cloud_spacing_m``, each point with the index of its ``scan``;
:mod:`~forestmap_assets.core.mapping.point_cloud`) and the tree list as ``trees.geojson`` (local
coordinates, for GIS users). Every file is written under a temporary name and renamed into place.
"""

from __future__ import annotations

import hashlib
import json
import os
import uuid
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd

from forestmap_assets.access import load_asset
from forestmap_assets.io.campaign import Campaign

POSES_COLUMNS = [
    "scan",
    "x",
    "y",
    "z",
    "heading_deg",
    "sd_x",
    "sd_y",
    "sd_z",
    "sd_heading_deg",
    "registered",
]
REGISTRATION_COLUMNS = [
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
    "peak_dx",
    "peak_dy",
    "peak_dz",
    "peak_dheading_deg",
    "log_score",
    "n_points",
    "seconds",
    "status",
    "reason",
]
RESIDUAL_COLUMNS = [
    "scan",
    "reference",
    "ex",
    "ey",
    "ez",
    "eheading_deg",
    "rx",
    "ry",
    "rz",
    "rheading",
    "verdict",
]
TREE_COLUMNS = ["tree_id", "x", "y", "z", "dbh_m", "n_scans", "n_cylinders", "visible_length_m"]
# trees.geojson: the trees.csv columns plus why a DBH is missing or how it was obtained
# off breast height (empty for a DBH at breast height; not in trees.csv, whose header is fixed)
TREE_GEOJSON_PROPERTIES = [*TREE_COLUMNS, "dbh_note"]
CYLINDER_COLUMNS = [
    "scan",
    "cylinder_id",
    "x0",
    "y0",
    "z0",
    "x1",
    "y1",
    "z1",
    "radius_m",
    "n_circles",
]


def atomic_path(path: Path, write: Callable[[Path], None]) -> Path:
    """Call ``write(tmp)`` then rename ``tmp`` to ``path``; remove ``tmp`` on failure."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{uuid.uuid4().hex[:8]}{path.suffix}")
    try:
        write(tmp)
        os.chmod(tmp, 0o644)  # helpers writing through mkstemp leave 0600
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def write_csv(df: pd.DataFrame, path: Path, columns: list[str]) -> Path:
    """CSV with exactly ``columns``; booleans as true/false, NaN as empty."""
    out = df.reindex(columns=columns).copy()
    for c in out.columns:
        if out[c].dtype == bool:
            out[c] = out[c].map({True: "true", False: "false"})
    return atomic_path(
        path, lambda tmp: out.to_csv(tmp, index=False, float_format="%.6g", na_rep="")
    )


EXPORTS = (
    "poses.csv",
    "registrations.csv",
    "residuals.csv",
    "trees.csv",
    "cylinders.parquet",
    "elevation.npz",
    "elevation.png",
    "trees.geojson",
    "cloud.laz",
    "cloud.ply",
    "map.png",
    "report.html",
)


EXPORTS_STAMP = ".forestmap-exports.json"


def exports_key(campaign: Campaign, state: int, options: dict) -> str:
    """What the exports of a run depend on: the campaign, the newest stored stage (``state``),
    the export options and the code that writes them (``outputs/``)."""
    h = hashlib.sha256(repr((str(campaign.root), campaign.key, state, sorted(options.items()))).encode())
    for src in sorted(Path(__file__).parent.rglob("*.py")):
        h.update(src.read_bytes())
    return h.hexdigest()[:24]


def exports_current(out: str | Path, key: str) -> bool:
    """Whether ``out`` holds the exports of ``key`` with every file still in place."""
    stamp = Path(out) / EXPORTS_STAMP
    try:
        doc = json.loads(stamp.read_text())
    except (OSError, ValueError):
        return False
    return doc.get("key") == key and all((Path(out) / n).is_file() for n in doc.get("files", []))


def write_exports_stamp(out: str | Path, key: str, written: list[Path]) -> None:
    """Record what :func:`write_exports` wrote (:func:`exports_current` reads it)."""
    out = Path(out)
    doc = {"key": key, "files": sorted(p.name for p in written)}
    atomic_path(out / EXPORTS_STAMP, lambda tmp: tmp.write_text(json.dumps(doc)))


def write_exports(
    campaign: Campaign,
    out: str | Path,
    *,
    cloud_spacing_m: float | None = 0.05,
    picture: bool = True,
    report: bool = True,
    progress=None,
    timings: pd.DataFrame | None = None,
    map_only: bool = False,
    stored: dict | None = None,
    pieces: bool = False,
) -> list[Path]:
    """Write every export that the stored assets allow; return the paths.

    ``map.png`` is rendered in a thread beside the other files (:class:`_MapPicture`), and so
    are the report's figures (``pieces``, and always before ``report.html``:
    :func:`~forestmap_assets.outputs.report.draw_report_pieces`).

    ``stored``: a dict that keeps the assets read (by name) and is read from where it has them,
    so that a report written later (:func:`~forestmap_assets.outputs.report.write_report`)
    need not read them again.

    ``map_only``: all but report.html (the map's files, written before the where-to-scan-next
    stages end, issue 16; :func:`~forestmap_assets.outputs.report.write_report` follows).

    ``cloud_spacing_m``: voxel size of the point cloud exports (0 keeps every point, None
    writes no cloud). ``picture``: render ``map.png``; ``report``: write ``report.html``
    with ``timings``, seconds per stage). ``progress``: a callable or
    :class:`~forestmap_assets.outputs.progress.Progress` (a bar over the files)."""
    from forestmap_assets.core.features.elevation import elevation_from_table
    from forestmap_assets.outputs.elevation_files import save_elevation_npz
    from forestmap_assets.outputs.figures.common import save_png
    from forestmap_assets.outputs.figures.elevation import elevation_figure
    from forestmap_assets.outputs.progress import as_progress

    prog = as_progress(progress)
    out = Path(out)
    written: list[Path] = []
    stored = {} if stored is None else stored  # read once, for the report too
    for name in ("optimal_map", "refined_registrations", "residual_checks", "tree_list", "integrated_map"):
        if name not in stored:
            stored[name] = load_asset(name, campaign=campaign)
    omap, refined = stored["optimal_map"], stored["refined_registrations"]  # the links that fed the map
    poses = omap["poses"]
    regs = refined.get("registrations", pd.DataFrame(columns=REGISTRATION_COLUMNS))  # none: 1 scan
    residuals, trees, integrated = stored["residual_checks"], stored["tree_list"], stored["integrated_map"]
    cylinders = integrated["cylinders"].reindex(columns=CYLINDER_COLUMNS)
    grid = elevation_from_table(integrated["elevation"])
    reference = campaign.scan_ids[0]
    placed = int(poses["registered"].astype(bool).sum())
    n_cyl = len(integrated["cylinders"])
    title = (
        f"{campaign.name}: {placed} of {len(poses)} scans, {n_cyl} cylinders, {len(trees)} trees"
    )

    steps = [
        ("poses.csv", lambda p: write_csv(poses, p, POSES_COLUMNS)),
        ("registrations.csv", lambda p: write_csv(regs, p, REGISTRATION_COLUMNS)),
        ("residuals.csv", lambda p: write_csv(residuals, p, RESIDUAL_COLUMNS)),
        ("trees.csv", lambda p: write_csv(trees, p, TREE_COLUMNS)),
        (
            "cylinders.parquet",
            lambda p: atomic_path(p, lambda tmp: cylinders.to_parquet(tmp, index=False)),
        ),
        ("elevation.npz", lambda p: atomic_path(p, lambda tmp: save_elevation_npz(tmp, grid))),
        (
            "elevation.png",
            lambda p: save_png(
                elevation_figure(
                    grid,
                    poses,
                    trees,
                    title=f"{campaign.name}: ground elevation (lowest hit), "
                    f"frame of scan {reference}",
                    reference=reference,
                ),
                p,
                dpi=120,
            ),
        ),
        ("trees.geojson", lambda p: write_geojson(trees, p, campaign)),
    ]
    if cloud_spacing_m is not None:
        steps.append(
            ("cloud.laz + cloud.ply", lambda p: write_clouds(campaign, poses, out, cloud_spacing_m))
        )
    report = report and not map_only
    picture_job = _MapPicture(out / "map.png", integrated["cylinders"], grid, poses, title=title,
                              reference=reference) if picture else None
    try:
        with prog.bar(len(steps) + bool(picture) + report, "exports", unit="file") as bar:
            for name, write in steps:
                result = write(out / name)
                written.extend(result if isinstance(result, list) else [result])
                bar.update(note=name)
            if pieces or report:
                _draw_pieces(campaign, out, stored)
            if picture_job is not None:
                written.append(picture_job.join())
                bar.update(note="map.png")
            if report:
                from forestmap_assets.outputs.report import write_report

                written.append(write_report(campaign, out, timings=timings, stored=stored))
                bar.update(note="report.html")
    finally:
        if picture_job is not None:
            picture_job.thread.join()
    return written


class _MapPicture:
    """``map.png`` rendered by VTK in a thread while the calling thread writes the other files
    and draws the report's figures: VTK lets go of the GIL while it renders (a rendered
    survey's map 1.0 s and report figures 0.9 s took 1.2 s side by side against 1.85 s one after
    the other, issue 16). When VTK cannot render, :meth:`join` draws the matplotlib picture in
    the calling thread (matplotlib's figures are not for two threads at once)."""

    def __init__(self, path: Path, cylinders, grid, poses, **kwargs):
        import threading

        self.args, self.kwargs, self.error = (path, cylinders, grid, poses), kwargs, None
        self.thread = threading.Thread(target=self._render, name="map.png", daemon=True)
        self.thread.start()

    def _render(self) -> None:
        from forestmap_assets.outputs.render import render_map

        try:
            render_map(*self.args, fallback=False, **self.kwargs)
        except Exception as exc:  # noqa: BLE001 - join() draws the fallback picture
            self.error = exc

    def join(self) -> Path:
        self.thread.join()
        if self.error is None:
            return self.args[0]
        from forestmap_assets.outputs.render import save_map_mpl

        return save_map_mpl(*self.args, title=self.kwargs.get("title", ""))


def _draw_pieces(campaign: Campaign, out: Path, stored: dict) -> None:
    """The report's figures, kept in ``stored`` for ``report.html``; a failure is left to the
    report, which draws them again and says why."""
    from forestmap_assets.outputs.report import PIECES, draw_report_pieces

    try:
        draw_report_pieces(campaign, out, stored)
    except Exception:  # noqa: BLE001
        stored.pop(PIECES, None)


def write_geojson(trees: pd.DataFrame, path: Path, campaign: Campaign) -> Path:
    """The tree list as a GeoJSON FeatureCollection of Points ``[x, y, z]`` in the campaign's
    local frame (metres, levelled frame of the reference scan; no geographic CRS, which the
    foreign member ``forestmap`` states), every ``trees.csv`` column and ``dbh_note`` as a
    property (``null`` from a tree list stored before the column existed)."""
    features = []
    for row in trees.reindex(columns=TREE_GEOJSON_PROPERTIES).itertuples(index=False):
        props = {c: _json_value(getattr(row, c)) for c in TREE_GEOJSON_PROPERTIES}
        coords = [_json_value(row.x), _json_value(row.y), _json_value(row.z)]
        features.append(
            {
                "type": "Feature",
                "id": props["tree_id"],
                "geometry": {"type": "Point", "coordinates": [c for c in coords if c is not None]},
                "properties": props,
            }
        )
    doc = {
        "type": "FeatureCollection",
        "name": f"{campaign.name} trees",
        "forestmap": {
            "frame": f"local levelled frame of scan {campaign.scan_ids[0]}",
            "units": "m",
            "crs": None,
            "z": "ground elevation under the stem",
            "campaign": campaign.name,
        },
        "features": features,
    }
    return atomic_path(
        path, lambda tmp: tmp.write_text(json.dumps(doc, indent=1), encoding="utf-8")
    )


def _json_value(v):
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(v) if np.isfinite(v) else None
    if isinstance(v, (np.bool_, bool)):
        return bool(v)
    return v


def campaign_cloud(campaign: Campaign, poses: pd.DataFrame, spacing_m: float) -> pd.DataFrame:
    """The registered point cloud of the campaign from the stored range images' levelled points
    (their float32 ``x, y, z``, with intensity and colour where stored; see
    :func:`~forestmap_assets.core.mapping.point_cloud.registered_cloud`)."""
    from forestmap_assets.core.mapping.point_cloud import EXTRA_COLUMNS, registered_cloud

    placed = set(poses.loc[poses["registered"].astype(bool), "scan"])
    scans = {}
    for sid in campaign.scan_ids:
        if sid not in placed:
            continue
        try:
            scans[sid] = load_asset("range_images", campaign=campaign, scan=sid,
                                    columns=["x", "y", "z", *EXTRA_COLUMNS])
        except FileNotFoundError:
            continue
    return registered_cloud(scans, poses, spacing_m, scan_ids=campaign.scan_ids)


def write_clouds(
    campaign: Campaign, poses: pd.DataFrame, out: Path, spacing_m: float
) -> list[Path]:
    """``cloud.laz`` and ``cloud.ply`` of :func:`campaign_cloud`."""
    cloud = campaign_cloud(campaign, poses, spacing_m)
    note = (
        f"forestmap campaign {campaign.name}, frame of scan {campaign.scan_ids[0]}, "
        f"spacing {spacing_m:g} m"
    )
    return [
        write_laz(cloud, out / "cloud.laz", campaign.scan_ids, note),
        write_ply(cloud, out / "cloud.ply", campaign.scan_ids, note),
    ]


def write_laz(cloud: pd.DataFrame, path: Path, scan_ids: list[str], note: str = "") -> Path:
    """LAS 1.4 (compressed when ``path`` ends in .laz) with millimetre scales, an extra
    dimension ``scan`` (uint16 index into ``scan_ids``, also in ``point_source_id``), RGB
    (16 bit) and intensity when the cloud has them, and a VLR ``forestmap/1`` holding the
    scan ids as JSON."""
    import laspy

    has_rgb = all(c in cloud for c in "rgb")
    header = laspy.LasHeader(point_format=7 if has_rgb else 6, version="1.4")
    header.add_extra_dim(
        laspy.ExtraBytesParams(name="scan", type=np.uint16, description="scan index")
    )
    xyz = cloud[["x", "y", "z"]].to_numpy(np.float64)
    header.offsets = np.floor(xyz.min(axis=0)) if len(xyz) else np.zeros(3)
    header.scales = np.array([0.001, 0.001, 0.001])
    header.vlrs.append(
        laspy.VLR(
            user_id="forestmap",
            record_id=1,
            description="scan ids (JSON)",
            record_data=json.dumps({"scan_ids": list(scan_ids), "note": note}).encode(),
        )
    )
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    scan = cloud["scan"].to_numpy(np.uint16)
    las.scan = scan
    las.point_source_id = scan
    if "intensity" in cloud:
        inten = cloud["intensity"].to_numpy(np.float64)
        top = np.nanmax(inten) if len(inten) and np.isfinite(inten).any() else 1.0
        las.intensity = np.clip(
            np.nan_to_num(inten / (top if top > 0 else 1.0)) * 65535, 0, 65535
        ).astype(np.uint16)
    if has_rgb:
        las.red, las.green, las.blue = (cloud[c].to_numpy(np.uint16) * 257 for c in "rgb")
    compress = path.suffix.lower() == ".laz"
    return atomic_path(path, lambda tmp: las.write(str(tmp), do_compress=compress))


def write_ply(cloud: pd.DataFrame, path: Path, scan_ids: list[str], note: str = "") -> Path:
    """Binary little-endian PLY: ``x y z`` (double), ``red green blue`` (uchar) and
    ``intensity`` (float) when present, ``scan`` (ushort index into ``scan_ids``; one header
    comment ``scan <index> <id>`` per scan)."""
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    props = ["property double x", "property double y", "property double z"]
    if all(c in cloud for c in "rgb"):
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        props += ["property uchar red", "property uchar green", "property uchar blue"]
    if "intensity" in cloud:
        fields.append(("intensity", "<f4"))
        props.append("property float intensity")
    fields.append(("scan", "<u2"))
    props.append("property ushort scan")
    data = np.empty(len(cloud), dtype=fields)
    source = {"red": "r", "green": "g", "blue": "b"}
    for name, _ in fields:
        data[name] = cloud[source.get(name, name)].to_numpy()
    comments = [f"comment {note}"] if note else []
    comments += [f"comment scan {i} {sid}" for i, sid in enumerate(scan_ids)]
    header = (
        "\n".join(
            [
                "ply",
                "format binary_little_endian 1.0",
                *comments,
                f"element vertex {len(cloud)}",
                *props,
                "end_header",
            ]
        )
        + "\n"
    )

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as fh:
            fh.write(header.encode("ascii"))
            fh.write(data.tobytes())

    return atomic_path(path, write)


def read_ply(path: str | Path) -> tuple[pd.DataFrame, list[str]]:
    """Read a PLY written by :func:`write_ply`: the vertex table and the header comments."""
    raw = Path(path).read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    lines = raw[:end].decode("ascii").splitlines()
    types = {
        "double": "<f8",
        "float": "<f4",
        "uchar": "u1",
        "ushort": "<u2",
        "int": "<i4",
        "uint": "<u4",
    }
    fields = [(ln.split()[2], types[ln.split()[1]]) for ln in lines if ln.startswith("property ")]
    count = int(next(ln.split()[2] for ln in lines if ln.startswith("element vertex")))
    data = np.frombuffer(raw, dtype=fields, count=count, offset=end)
    return pd.DataFrame({name: data[name] for name, _ in fields}), [
        ln[8:] for ln in lines if ln.startswith("comment ")
    ]
