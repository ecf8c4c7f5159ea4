"""Shared pieces of the thin Dagster layer: partitions, versions, metadata helpers."""

from __future__ import annotations

import base64
import hashlib
import io
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
from dagster import AssetKey, DataVersion, DynamicPartitionsDefinition, MetadataValue

from ..campaign import Campaign

# Bump a stage's number when its code changes meaning; the parameter hash is appended.
CODE_VERSIONS: dict[str, str] = {
    "range_images": "1",
    "segments": "1",
    "circle_models": "1",
    "cylinder_segments": "1",
    "line_segments": "1",
    "elevation_maps": "1",
    "submaps": "1",
    "candidate_pairs": "1",
    "pairwise_registrations": "1",
    "optimal_map": "1",
    "residual_checks": "1",
    "integrated_map": "1",
    "tree_list": "1",
}

# Which parameter sections each stage reads (their hash enters the code version).
STAGE_PARAMS: dict[str, tuple[str, ...]] = {
    "range_images": (),
    "segments": ("segmentation",),
    "circle_models": ("segmentation", "circles"),
    "cylinder_segments": ("cylinders",),
    "line_segments": ("lines",),
    "elevation_maps": ("elevation",),
    "submaps": ("submaps",),
    "candidate_pairs": ("registration",),
    "pairwise_registrations": ("registration", "elevation"),
    "optimal_map": ("mapping",),
    "residual_checks": ("mapping",),
    "integrated_map": ("elevation",),
    "tree_list": (),
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
    ("candidate_pairs", "campaign"),
    ("pairwise_registrations", "campaign"),
    ("optimal_map", "campaign"),
    ("residual_checks", "campaign"),
    ("integrated_map", "campaign"),
    ("tree_list", "campaign"),
)


def scan_partitions(campaign: Campaign) -> DynamicPartitionsDefinition:
    """Per-scan partitions of one campaign (dynamic: adding a scan adds one partition)."""
    return DynamicPartitionsDefinition(name=f"{campaign.key}__scans")


def asset_key(campaign: Campaign, stage: str) -> AssetKey:
    return AssetKey([campaign.key, stage])


def code_version(campaign: Campaign, stage: str) -> str:
    """Stage code version plus the hash of its resolved parameter sections."""
    digests = [campaign.params.digest(s) for s in STAGE_PARAMS[stage]]
    return "-".join([f"v{CODE_VERSIONS[stage]}", *digests])


def data_version(obj: Any) -> DataVersion:
    """Content hash of an asset output (table or bundle of tables)."""
    h = hashlib.sha256()

    def feed(table: pd.DataFrame | pa.Table) -> None:
        if isinstance(table, pd.DataFrame):
            table = pa.Table.from_pandas(table, preserve_index=False)
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


def png_metadata(fig) -> MetadataValue:
    """A matplotlib figure as an inline Markdown image for the Dagster UI."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    data = base64.b64encode(buf.getvalue()).decode()
    return MetadataValue.md(f"![image](data:image/png;base64,{data})")


def range_image_figure(range_m: np.ndarray, title: str, overlay: np.ndarray | None = None):
    """Small picture of a range image, optionally with a boolean mask overlaid in red."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows, cols = range_m.shape
    fig, ax = plt.subplots(figsize=(8, max(1.5, 8 * rows / max(cols, 1))))
    img = ax.imshow(range_m, cmap="viridis", aspect="auto", interpolation="nearest")
    if overlay is not None and overlay.any():
        rgba = np.zeros(overlay.shape + (4,))
        rgba[overlay] = (1.0, 0.1, 0.1, 0.9)
        ax.imshow(rgba, aspect="auto", interpolation="nearest")
    fig.colorbar(img, ax=ax, label="range (m)", fraction=0.03)
    ax.set_title(title)
    ax.set_xlabel("column (azimuth)")
    ax.set_ylabel("row (elevation)")
    return fig
