"""A simulated campaign as scanner software exports it (issue 18's test data, made here): one E57
holding every scan with each scan's pose (inclinometer tilt, compass heading and rough position),
or one point-cloud file per scan already placed in a project (map) frame at UTM-sized
coordinates, with the scanner's pose given in ``campaign.yaml``.

Both rewrite a campaign folder written by :func:`~forestmap_assets.sim.campaign.simulate_campaign`
in place; ``truth/`` is unchanged (poses in the levelled frame of the first scan, which is still
the frame of forestmap's outputs).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from forestmap_assets.core.geometry import roll_pitch_heading, rotation_zyx
from forestmap_assets.io.campaign import MANIFEST, load_campaign
from forestmap_assets.io.readers import read_scan
from forestmap_assets.io.writers import write_e57_scans, write_scan

# A project frame like a UTM zone's: large coordinates and a turn against the scans' frame
PROJECT_ORIGIN = (512345.12, 6712345.67, 101.3)
PROJECT_TURN_DEG = 37.0


def _truth_poses(folder: Path, tilts: dict[str, tuple[float, float]]) -> dict[str, np.ndarray]:
    """Scanner-to-truth-frame 4x4 of every scan: truth position and heading, campaign tilt."""
    truth = pd.read_csv(folder / "truth" / "poses.csv")
    out = {}
    for r in truth.itertuples(index=False):
        m = np.eye(4)
        roll, pitch = tilts.get(str(r.scan), (0.0, 0.0))
        m[:3, :3] = rotation_zyx(roll, pitch, r.heading_deg)
        m[:3, 3] = r.x, r.y, r.z
        out[str(r.scan)] = m
    return out


def _project(origin=PROJECT_ORIGIN, turn_deg: float = PROJECT_TURN_DEG) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = rotation_zyx(0.0, 0.0, turn_deg)
    m[:3, 3] = origin
    return m


def _rewrite_manifest(folder: Path, entries: list[dict]) -> None:
    doc = yaml.safe_load((folder / MANIFEST).read_text())
    doc["scans"] = entries
    doc.pop("pairs", None)
    (folder / MANIFEST).write_text(yaml.safe_dump(doc, sort_keys=False, default_flow_style=None))


def pack_e57(folder: str | Path, *, file_name: str = "survey.e57",
             prior_error: tuple[float, float] = (0.5, 5.0), seed: int = 0,
             project: bool = True, with_prior: bool = True) -> Path:
    """Put every scan of ``folder`` into one E57 (``scans/<file_name>``) whose scans carry their
    poses: the campaign's tilt, the true heading and position with a rough error (N(0, m) per
    axis, N(0, deg) heading) in a project frame (``project``); ``with_prior=False``: the tilt only
    (identity heading and position, as an unregistered export). Entries: ``e57_scan: i``, no
    ``tilt_deg``, ``a_priori`` or ``pairs`` (the file says them)."""
    folder = Path(folder)
    camp = load_campaign(folder)
    rng = np.random.default_rng(seed)
    to_project = _project() if project else np.eye(4)
    poses = _truth_poses(folder, {s.id: s.tilt_deg for s in camp.scans})
    items, entries = [], []
    for i, s in enumerate(camp.scans):
        image = read_scan(s.path, angular_step_deg=camp.angular_step_deg)
        err = np.eye(4)
        err[:3, :3] = rotation_zyx(0.0, 0.0, rng.normal(0.0, prior_error[1]))
        err[:3, 3] = rng.normal(0.0, prior_error[0], 3) * [1, 1, 0.2]
        if with_prior:
            pose = to_project @ _with_error(poses[s.id], err)
        else:
            pose = np.eye(4)
            pose[:3, :3] = rotation_zyx(*s.tilt_deg, 0.0)
        items.append((s.id, image, pose))
        entries.append({"id": s.id, "path": f"scans/{file_name}", "e57_scan": i})
    write_e57_scans(folder / "scans" / file_name, items)
    for s in camp.scans:
        if s.path.name != file_name:
            s.path.unlink()
    _rewrite_manifest(folder, entries)
    return folder / "scans" / file_name


def _with_error(scanner: np.ndarray, err: np.ndarray) -> np.ndarray:
    """``scanner`` with a heading error about its own vertical axis and a position error."""
    out = scanner.copy()
    out[:3, :3] = err[:3, :3] @ scanner[:3, :3]
    out[:3, 3] = scanner[:3, 3] + err[:3, 3]
    return out


def place_in_project_frame(folder: str | Path, fmt: str = "las", *,
                           origin=PROJECT_ORIGIN, turn_deg: float = PROJECT_TURN_DEG) -> Path:
    """Rewrite every scan as a ``fmt`` point cloud in a project frame (UTM-sized coordinates,
    turned by ``turn_deg``), with each entry's ``pose`` saying where its scanner stood (the true
    pose, tilt included): the files a surveyor gets from registration software."""
    folder = Path(folder)
    camp = load_campaign(folder)
    to_project = _project(origin, turn_deg)
    poses = _truth_poses(folder, {s.id: s.tilt_deg for s in camp.scans})
    entries = []
    for s in camp.scans:
        image = read_scan(s.path, angular_step_deg=camp.angular_step_deg)
        pose = to_project @ poses[s.id]
        out = s.path.with_suffix(f".{fmt}")
        write_scan(out, image, to_file=pose)
        if out != s.path:
            s.path.unlink()
        roll, pitch, heading = roll_pitch_heading(pose[:3, :3])
        x, y, z = (float(v) for v in pose[:3, 3])
        entries.append({"id": s.id, "path": out.relative_to(folder).as_posix(),
                        "pose": {"x": round(x, 4), "y": round(y, 4), "z": round(z, 4),
                                 "roll_deg": round(roll, 6), "pitch_deg": round(pitch, 6),
                                 "heading_deg": round(heading, 6)}})
    _rewrite_manifest(folder, entries)
    return folder
