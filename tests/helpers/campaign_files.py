"""Small campaign folders for the orchestration and input tests: an organised npz scan of a wall
and a stem, and a campaign.yaml over a few of them."""

from __future__ import annotations

import numpy as np


def write_npz_scan(path, rows=30, cols=120, seed=0, with_rgb=False):
    """A small organised range image: a wall at 8 m with a 'stem' at 4 m, sky above."""
    rng = np.random.default_rng(seed)
    az = np.linspace(-60.0, 60.0, cols)
    el = np.linspace(20.0, -20.0, rows)
    r = np.full((rows, cols), 8.0, np.float32) + rng.normal(0, 0.01, (rows, cols)).astype(np.float32)
    r[:, cols // 2 - 3 : cols // 2 + 3] = 4.0
    r[:3] = np.nan
    arrays = {"range": r, "azimuth_deg": az, "elevation_deg": el}
    if with_rgb:
        arrays["rgb"] = rng.integers(0, 255, (rows, cols, 3), dtype=np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **arrays)
    return path


def write_campaign(root, scans=("T", "S"), extra="", **npz):
    """A campaign folder with npz scans and a manifest (``extra`` appended verbatim)."""
    lines = ["name: test-campaign", "environment: forest", "scans:"]
    for i, sid in enumerate(scans):
        write_npz_scan(root / "scans" / f"{sid}.npz", seed=i, **npz)
        lines.append(f"  - {{id: {sid}, path: scans/{sid}.npz}}")
    (root / "campaign.yaml").write_text("\n".join(lines) + "\n" + extra)
    return root
