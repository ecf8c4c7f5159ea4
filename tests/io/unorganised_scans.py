"""Unorganised scans that resemble a real scanner's export (issue 18), with the truth of a
simulated campaign: the same scan positions as :func:`forestmap_assets.sim.simulate_campaign`
writes (organised ``.npz``, truth, labels), plus per scan the cloud of
:meth:`VirtualScanner.scan_points` (beams jittered in angle, returns dropped at random), and
writers of LAS/LAZ files in the scanner frame. Used by ``tests/io/test_big_scans.py`` and
``benchmarks/bench_big_scan.py``."""

from __future__ import annotations

from pathlib import Path
from unittest import mock

import numpy as np
import yaml

import forestmap_assets.sim.campaign as sim_campaign
from forestmap_assets.sim import simulate_campaign
from forestmap_assets.sim.scanner import VirtualScanner


def simulate_with_clouds(out: Path, *, seed: int, jitter_steps: float = 0.3, dropout: float = 0.3,
                         **campaign_kwargs) -> tuple[Path, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """A simulated campaign (``simulate_campaign(out, seed=seed, **campaign_kwargs)``) and, per
    scan id, the unorganised scanner-frame cloud (xyz, intensity) of the same scan position."""
    clouds: list[tuple[np.ndarray, np.ndarray]] = []

    class Recording(VirtualScanner):
        def scan(self, pose, seed=0, **kwargs):
            result = super().scan(pose, seed, **kwargs)
            if not kwargs:  # a campaign scan: its unorganised twin from the same position
                rng = np.random.default_rng([seed_base, len(clouds)])
                clouds.append(self.scan_points(pose, rng, jitter_steps=jitter_steps,
                                               dropout=dropout))
            return result

    seed_base = 1000 + seed
    with mock.patch.object(sim_campaign, "VirtualScanner", Recording):
        camp = simulate_campaign(out, seed=seed, **campaign_kwargs)
    ids = [s["id"] for s in yaml.safe_load((camp / "campaign.yaml").read_text())["scans"]]
    return camp, dict(zip(ids, clouds, strict=True))


def write_las(path: Path, xyz: np.ndarray, intensity: np.ndarray | None = None) -> Path:
    """Points (scanner frame, float64) to LAS/LAZ (by extension) as scanner software exports
    them: 0.1 mm coordinates, 16-bit intensity (reflectance 0-1 scaled to 65535)."""
    import laspy

    header = laspy.LasHeader(point_format=1 if intensity is not None else 0, version="1.2")
    header.scales = np.array([1e-4, 1e-4, 1e-4])
    header.offsets = np.zeros(3)
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if intensity is not None:
        las.intensity = np.clip(np.rint(np.asarray(intensity) * 65535), 0, 65535).astype(np.uint16)
    las.write(str(path), do_compress=Path(path).suffix.lower() == ".laz")
    return Path(path)


def thinned(xyz: np.ndarray, intensity: np.ndarray | None, keep: float, seed: int = 0):
    """A random share ``keep`` of the points (a sub-sampled export)."""
    sel = np.random.default_rng(seed).random(len(xyz)) < keep
    return xyz[sel], (None if intensity is None else intensity[sel])
