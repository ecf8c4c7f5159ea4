"""Shared pieces of the thin Dagster layer: partitions, jobs, versions, checks, metadata."""

from __future__ import annotations

import base64
import hashlib
import json
from dataclasses import asdict, dataclass
from typing import Any

import pandas as pd
import pyarrow as pa
from dagster import (
    AssetCheckResult,
    AssetCheckSeverity,
    AssetCheckSpec,
    AssetIn,
    AssetKey,
    DataVersion,
    DynamicPartitionsDefinition,
    MetadataValue,
)

from forestmap_assets.io.campaign import Campaign
from forestmap_assets.params.men import ExplorationConfig, OcclusionConfig

# Bump a stage's number when its code changes meaning; the parameter hash is appended.
CODE_VERSIONS: dict[str, str] = {
    "range_images": "4",
    "segments": "1",
    "circle_models": "2",
    "cylinder_segments": "3",
    "line_segments": "1",
    "elevation_maps": "1",
    "submaps": "1",
    "refine_clouds": "5",
    "candidate_pairs": "2",
    "pairwise_registrations": "4",
    "refined_registrations": "8",
    "retry_pairs": "1",
    "optimal_map": "7",
    "residual_checks": "1",
    "scan_tilts": "1",
    "integrated_map": "2",
    "tree_list": "15",
}

# Which parameter sections each stage reads (their hash enters the code version).
STAGE_PARAMS: dict[str, tuple[str, ...]] = {
    "range_images": ("range_images",),
    "segments": ("segmentation",),
    "circle_models": ("segmentation", "circles"),
    "cylinder_segments": ("cylinders",),
    "line_segments": ("lines",),
    "elevation_maps": ("elevation",),
    "submaps": ("submaps",),
    "refine_clouds": ("refine",),
    "candidate_pairs": ("registration",),
    "pairwise_registrations": ("registration", "elevation"),
    "refined_registrations": ("refine",),
    "retry_pairs": ("registration",),
    "optimal_map": ("mapping", "refine"),  # refine: the beam (objective_scale.scale_floor)
    "residual_checks": ("mapping",),
    "scan_tilts": ("mapping",),
    "integrated_map": ("elevation",),
    "tree_list": ("trees",),
}

# The pipeline's assets in DESIGN.md section 5 order, with their granularity.
PIPELINE: tuple[tuple[str, str], ...] = (
    ("range_images", "scan"),
    ("segments", "scan"),
    ("circle_models", "scan"),
    ("cylinder_segments", "scan"),
    ("line_segments", "scan"),
    ("elevation_maps", "scan"),
    ("submaps", "scan"),
    ("refine_clouds", "scan"),  # issue 16/17: each scan prepared once for the pairs' refinement
    ("candidate_pairs", "campaign"),
    ("pairwise_registrations", "pair"),
    ("refined_registrations", "pair"),  # Men 2012 ch. 5: fine registration on raw points
    ("retry_pairs", "campaign"),  # issue 17: partners for the scans the pairs left unplaced
    ("optimal_map", "campaign"),
    ("residual_checks", "campaign"),
    ("scan_tilts", "campaign"),  # scans levelled from their shared stems (beyond the thesis)
    ("integrated_map", "campaign"),
    ("tree_list", "campaign"),
    ("occlusion_boundaries", "scan"),  # Men 2012 ch. 3, 6: where to scan next
    ("next_vantage_points", "campaign"),
)


def scan_partitions(campaign: Campaign) -> DynamicPartitionsDefinition:
    """Per-scan partitions of one campaign (dynamic: adding a scan adds one partition)."""
    return DynamicPartitionsDefinition(name=f"{campaign.key}__scans")


def pair_partitions(campaign: Campaign) -> DynamicPartitionsDefinition:
    """Per-pair partitions of one campaign (issue 17): keys ``<scan>__<reference>``, the set
    kept equal to the pairs ``candidate_pairs`` and ``retry_pairs`` ask for."""
    return DynamicPartitionsDefinition(name=f"{campaign.key}__pairs")


PAIR_SEPARATOR = "__"


def pair_key(scan: str, reference: str) -> str:
    return f"{scan}{PAIR_SEPARATOR}{reference}"


def split_pair_key(key: str, scan_ids) -> tuple[str, str]:
    """``(scan, reference)`` of a pair key; scan ids may hold ``__`` themselves, so the split is
    the one whose two halves are both scans of the campaign."""
    ids = set(scan_ids)
    parts = key.split(PAIR_SEPARATOR)
    for k in range(1, len(parts)):
        a, b = PAIR_SEPARATOR.join(parts[:k]), PAIR_SEPARATOR.join(parts[k:])
        if a in ids and b in ids:
            return a, b
    raise ValueError(f"pair {key!r} does not name two scans of the campaign")


def screened(campaign: Campaign) -> bool:
    """Whether the campaign's pairs are chosen by stem-layout screening (no a priori pairs or
    poses, ``registration.screening`` on): then ``retry_pairs`` exists (issue 17)."""
    reg = campaign.params.registration
    no_prior = not campaign.pairs and any(s.a_priori is None for s in campaign.scans)
    return bool(no_prior and reg.screening and reg.screen_keep > 0)


def asset_key(campaign: Campaign, stage: str) -> AssetKey:
    return AssetKey([campaign.key, stage])


# Which entries of campaign.yaml (besides ``params``) each campaign-level stage reads (inferred):
# the ordered scan list (the first scan is the reference frame; adding or removing a scan changes
# what the stage computes), the a priori pairs and the a priori poses.
STAGE_MANIFEST: dict[str, tuple[str, ...]] = {
    "candidate_pairs": ("scans", "pairs", "a_priori"),
    "optimal_map": ("scans",),
}

SCAN_STAGES: tuple[str, ...] = tuple(s for s, g in PIPELINE if g == "scan")
PAIR_STAGES: tuple[str, ...] = tuple(s for s, g in PIPELINE if g == "pair")
CAMPAIGN_STAGES: tuple[str, ...] = tuple(s for s, g in PIPELINE if g == "campaign")


def manifest_digest(campaign: Campaign, entries: tuple[str, ...]) -> str:
    """Short hash of the named manifest entries (``scans``, ``pairs``, ``a_priori``)."""
    parts: dict[str, object] = {}
    if "scans" in entries:
        parts["scans"] = campaign.scan_ids
    if "pairs" in entries:
        parts["pairs"] = [(p.scan, p.reference, list(p.a_priori)) for p in campaign.pairs]
    if "a_priori" in entries:
        parts["a_priori"] = {s.id: list(s.a_priori) for s in campaign.scans if s.a_priori is not None}
    return hashlib.sha256(repr(sorted(parts.items())).encode()).hexdigest()[:16]


# The stages from Men (2012) version their settings (dataclasses of params.men), not sections
MEN_CODE_VERSIONS = {"occlusion_boundaries": "1", "next_vantage_points": "2"}


def occlusion_config(campaign: Campaign) -> OcclusionConfig:
    return OcclusionConfig.from_params(getattr(campaign.params, "occlusion", None))


def exploration_config(campaign: Campaign) -> ExplorationConfig:
    return ExplorationConfig.from_params(getattr(campaign.params, "exploration", None))


def _version(stage: str, *configs) -> str:
    text = json.dumps([asdict(c) for c in configs], sort_keys=True, default=str)
    return f"v{MEN_CODE_VERSIONS[stage]}-{hashlib.sha256(text.encode()).hexdigest()[:16]}"


def stage_version(campaign: Campaign, stage: str) -> str:
    """Code version of ``occlusion_boundaries`` / ``next_vantage_points`` (stage version plus the
    hash of its settings), as :func:`code_version` gives for the other stages."""
    if stage == "occlusion_boundaries":
        config = occlusion_config(campaign)
    else:
        config = exploration_config(campaign)
    return _version(stage, config)


def code_version(campaign: Campaign, stage: str) -> str:
    """Stage code version plus the hash of its resolved parameter sections and of the
    manifest entries it reads (``STAGE_MANIFEST``)."""
    if stage not in CODE_VERSIONS:  # the exploration stages (Men 2012) version their settings
        return stage_version(campaign, stage)
    digests = [campaign.params.digest(s) for s in STAGE_PARAMS[stage]]
    if STAGE_MANIFEST.get(stage):
        digests.append("m" + manifest_digest(campaign, STAGE_MANIFEST[stage]))
    return "-".join([f"v{CODE_VERSIONS[stage]}", *digests])


def job_name(campaign: Campaign, kind: str) -> str:
    """Name of a campaign's asset job: ``kind`` is ``scan`` (per-scan assets, partitioned by
    scan), ``pair`` (per-pair assets, partitioned by pair) or ``campaign`` (campaign-level
    assets)."""
    return f"{campaign.key}__{kind}_assets"


# Columns that record how long something took, not what was computed: left out of data versions
# so that re-running a stage that produces the same result does not make its downstream stale.
VOLATILE_COLUMNS: frozenset[str] = frozenset({"seconds"})


def data_version(obj: Any) -> DataVersion:
    """Content hash of an asset output (table or bundle of tables), ``VOLATILE_COLUMNS`` left out:
    XXH3 (128 bit), 20 GB/s here against SHA-256's 1.7 (a rendered scan's range image table,
    60 MB: 35 -> 3 ms; issue 16). A version is compared with versions, never trusted as a
    signature, so a fast non-cryptographic hash is enough."""
    import xxhash

    h = xxhash.xxh3_128()

    def feed(table: pd.DataFrame | pa.Table) -> None:
        if isinstance(table, pd.DataFrame):
            table = pa.Table.from_pandas(table, preserve_index=False)
        volatile = [c for c in table.column_names if c in VOLATILE_COLUMNS]
        if volatile:
            table = table.drop_columns(volatile)
        h.update(str(table.schema).encode())
        for meta in (table.schema.metadata or {}).items():
            h.update(b"".join(meta))
        for column in table.columns:
            for chunk in column.chunks:
                for buf in chunk.buffers():
                    if buf is not None:
                        h.update(memoryview(buf))

    if isinstance(obj, dict):
        for name in sorted(obj):
            h.update(name.encode())
            feed(obj[name])
    else:
        feed(obj)
    return DataVersion(h.hexdigest()[:24])


def picture_metadata(picture) -> MetadataValue:
    """A :class:`~forestmap_assets.outputs.figures.common.Picture` as inline Markdown for the
    Dagster UI: its caption, then the image."""
    data = base64.b64encode(picture.png).decode()
    caption = f"{picture.caption}\n\n" if picture.caption else ""
    return MetadataValue.md(f"{caption}![image](data:image/png;base64,{data})")


def png_metadata(fig) -> MetadataValue:
    """A (pyplot-free) matplotlib figure as an inline Markdown image for the Dagster UI."""
    from forestmap_assets.outputs.figures.common import Picture, png_bytes

    return picture_metadata(Picture(png_bytes(fig, dpi=80), ""))


# --- per-scan asset checks (circle_models, cylinder_segments) -------------------------------


@dataclass(frozen=True)
class ScanCheckThresholds:
    """Thresholds of the per-scan asset checks (inferred; the thesis reports no such limits).

    A scan with fewer valid circle models or cylinder segments than these can still be used,
    but its registrations rest on few stems (a 4-DoF alignment needs at least two well-separated
    stems; three make it checkable). A high share of rejected circle models usually means the
    environment preset or the noise level does not fit the scanner.
    """

    min_valid_circles: int = 50
    max_rejected_share: float = 0.8
    min_cylinders: int = 3


def scan_check_thresholds(campaign: Campaign) -> ScanCheckThresholds:
    """The campaign's check thresholds: ``params.checks`` where the parameter model has that
    section, else the defaults of :class:`ScanCheckThresholds`."""
    section = getattr(campaign.params, "checks", None)
    if section is None:
        return ScanCheckThresholds()
    names = ScanCheckThresholds.__dataclass_fields__
    return ScanCheckThresholds(**{k: getattr(section, k) for k in names if hasattr(section, k)})


def circle_check_specs(key: AssetKey) -> list[AssetCheckSpec]:
    """Checks of one scan's circle models (non-blocking: a weak scan is still registered or
    reported as not registered downstream)."""
    return [
        AssetCheckSpec("enough_valid_circles", asset=key, description="The scan has enough valid "
                       "circle models in the last iteration (ERROR when none, WARN when few)."),
        AssetCheckSpec("rejected_circle_share", asset=key, description="The share of circle models "
                       "rejected by the fit, size, convexity and symmetry tests is not too high "
                       "(WARN: preset or noise level may not fit the scanner)."),
    ]


def cylinder_check_specs(key: AssetKey) -> list[AssetCheckSpec]:
    return [
        AssetCheckSpec("enough_cylinders", asset=key, description="The scan has enough cylinder "
                       "segments to be registered (ERROR when none, WARN when few)."),
    ]


def circle_checks(table: pd.DataFrame, limits: ScanCheckThresholds) -> list[AssetCheckResult]:
    """Results of :func:`circle_check_specs` for one scan's ``circle_models`` table."""
    if len(table):
        last = table[table["iteration"] == table["iteration"].max()]
        valid = int(last["valid"].sum())
        share = float((~last["valid"].astype(bool)).mean())
    else:
        valid, share = 0, 0.0
    return [
        AssetCheckResult(
            check_name="enough_valid_circles", passed=valid >= limits.min_valid_circles,
            severity=AssetCheckSeverity.ERROR if valid == 0 else AssetCheckSeverity.WARN,
            metadata={"valid_circles": valid, "min_valid_circles": limits.min_valid_circles},
        ),
        AssetCheckResult(
            check_name="rejected_circle_share", passed=share <= limits.max_rejected_share,
            severity=AssetCheckSeverity.WARN,
            metadata={"rejected_share": round(share, 4), "max_rejected_share": limits.max_rejected_share},
        ),
    ]


def cylinder_checks(table: pd.DataFrame, limits: ScanCheckThresholds) -> list[AssetCheckResult]:
    """Results of :func:`cylinder_check_specs` for one scan's ``cylinder_segments`` table."""
    n = len(table)
    return [
        AssetCheckResult(
            check_name="enough_cylinders", passed=n >= limits.min_cylinders,
            severity=AssetCheckSeverity.ERROR if n == 0 else AssetCheckSeverity.WARN,
            metadata={"cylinders": n, "min_cylinders": limits.min_cylinders},
        ),
    ]


def all_scans(stage_key, columns: list[str] | None = None) -> AssetIn:
    """All scan partitions of a per-scan asset; a scan whose partition failed is left out.
    ``columns``: read only these columns of each stored table."""
    meta = {"allow_missing_partitions": True} | ({"columns": columns} if columns else {})
    return AssetIn(key=stage_key, metadata=meta)


def md_table(df: pd.DataFrame, floatfmt: str = ".3f") -> MetadataValue:
    if df.empty:
        return MetadataValue.md("_empty_")
    cols = list(df.columns)
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for row in df.itertuples(index=False):
        lines.append("| " + " | ".join(format(v, floatfmt) if isinstance(v, float) else str(v) for v in row) + " |")
    return MetadataValue.md("\n".join(lines))


def timed(fn):
    """Asset body wrapper: the step's compute seconds join its Output's metadata (``seconds``),
    with the CPU seconds of its thread (``cpu_seconds``: far fewer when the step waited for a
    core that other steps held; the threads Open3D starts for it, as in the normals of the
    refinement clouds, are not counted), so the profile of a run reads off the asset catalogue
    as well as the report (issue 16)."""
    import functools
    import inspect
    import time

    from dagster import Output

    def clocks() -> tuple[float, float]:
        return time.perf_counter(), time.thread_time()

    def stamp(result, start: tuple[float, float]):
        if isinstance(result, Output):
            (wall, cpu), (wall0, cpu0) = clocks(), start
            wall, cpu = wall - wall0, cpu - cpu0
            return result.with_metadata({**result.metadata, "seconds": round(wall, 3), "cpu_seconds": round(cpu, 3)})
        return result

    if inspect.isgeneratorfunction(fn):
        @functools.wraps(fn)
        def gen(*args, **kwargs):
            start = clocks()
            for item in fn(*args, **kwargs):
                yield stamp(item, start)
        return gen

    @functools.wraps(fn)
    def plain(*args, **kwargs):
        start = clocks()
        return stamp(fn(*args, **kwargs), start)
    return plain
