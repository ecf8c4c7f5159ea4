"""``forestmap init FOLDER_OR_E57 [--out CAMPAIGN]`` (DESIGN section 3): a ready ``campaign.yaml``
for a folder of scan files or a multi-scan E57, one entry per scan (per ``data3D`` entry of an
E57, ids from the scan names), with what the files say about poses, and a summary of what was found.

Only headers are read (E57 structure, LAS header, PLY/PCD header), so a folder of big scans is
listed in seconds.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

from forestmap_assets.io.campaign import MANIFEST, SCAN_EXTENSIONS, CampaignError
from forestmap_assets.io.scan_poses import e57_poses

# A cloud whose xy box is farther than this from the file's origin is in a project or map frame
PROJECT_FRAME_M = 1000.0


@dataclass
class Found:
    """One scan entry of the new manifest and what was learnt about it."""

    id: str
    path: str
    e57_scan: int | None = None
    points: int | None = None
    notes: list[str] = field(default_factory=list)


def _safe_id(text: str, taken: set[str]) -> str:
    base = re.sub(r"[^A-Za-z0-9_-]+", "_", text.strip()).strip("_") or "scan"
    sid, k = base, 2
    while sid in taken:
        sid, k = f"{base}_{k}", k + 1
    taken.add(sid)
    return sid


def _las_header(path: Path) -> tuple[int, list[float], list[float]] | None:
    try:
        import laspy

        with laspy.open(str(path)) as f:
            h = f.header
            return int(h.point_count), list(h.mins), list(h.maxs)
    except Exception:
        return None


def _scan_files(folder: Path, out: Path) -> list[Path]:
    outputs = (out / "outputs").resolve()
    files = []
    for p in sorted(folder.rglob("*")):
        if p.is_file() and p.suffix.lower() in SCAN_EXTENSIONS and not p.name.startswith("."):
            if outputs in p.resolve().parents or "truth" in p.relative_to(folder).parts:
                continue
            files.append(p)
    return files


def find_scans(source: Path, out: Path) -> list[Found]:
    """Every scan of ``source`` (a folder, or one E57 file) as manifest entries relative to
    ``out``."""
    files = [source] if source.is_file() else _scan_files(source, out)
    taken: set[str] = set()
    found: list[Found] = []
    for f in files:
        rel = Path(os.path.relpath(f.resolve(), out.resolve())).as_posix()
        ext = f.suffix.lower()
        if ext == ".e57":
            scans = e57_poses(f)
            if scans is None:
                found.append(Found(_safe_id(f.stem, taken), rel, notes=["E57 header unreadable"]))
                continue
            for i, (name, pose) in enumerate(scans):
                item = Found(_safe_id(name if len(scans) > 1 else f.stem, taken), rel,
                             i if len(scans) > 1 else None)
                if pose is None:
                    item.notes.append("no pose stored")
                else:
                    r, p = pose.tilt_deg
                    x, y, z, h = pose.a_priori
                    item.notes.append(f"pose in file: tilt {r:.2f}/{p:.2f} deg, heading {h:.1f} deg, "
                                      f"position {x:.2f} {y:.2f} {z:.2f}")
                found.append(item)
            continue
        item = Found(_safe_id(f.stem, taken), rel)
        if ext in (".las", ".laz"):
            head = _las_header(f)
            if head is None:
                item.notes.append("LAS header unreadable")
            else:
                item.points, lo, hi = head
                # a scanner-frame cloud lies within the scanner's reach of its origin
                gap = [max(lo[k], 0.0, -hi[k]) for k in (0, 1)]
                if (gap[0] ** 2 + gap[1] ** 2) ** 0.5 > PROJECT_FRAME_M:
                    item.notes.append(
                        f"points in a project frame (x {lo[0]:.1f}..{hi[0]:.1f}, y {lo[1]:.1f}.."
                        f"{hi[1]:.1f}): give `pose:` with where the scanner stood")
        found.append(item)
    return found


def _yaml_scalar(text: str) -> str:
    return f'"{text}"' if re.fullmatch(r"[0-9.eE+-]+|true|false|null|yes|no|on|off", text, re.I) else text


def manifest_text(name: str, found: list[Found]) -> str:
    """The ``campaign.yaml`` text: one entry per scan, notes as comments."""
    lines = [f"name: {_yaml_scalar(name)}", "environment: forest   # forest | outdoor | indoor",
             "scans:"]
    for item in found:
        for note in item.notes:
            lines.append(f"  # {item.id}: {note}")
        lines.append(f"  - id: {_yaml_scalar(item.id)}")
        lines.append(f"    path: {item.path}")
        if item.e57_scan is not None:
            lines.append(f"    e57_scan: {item.e57_scan}")
    return "\n".join(lines) + "\n"


def init_campaign(source: str | Path, out: str | Path | None = None, *,
                  force: bool = False) -> tuple[Path, list[Found]]:
    """Write ``out/campaign.yaml`` for ``source`` (default ``out``: the folder, or the E57's
    folder) and return its path and the entries. Raises :class:`CampaignError` (one line)."""
    src = Path(source).expanduser()
    if not src.exists():
        raise CampaignError(f"{src}: no such file or folder")
    if src.is_file() and src.suffix.lower() != ".e57":
        raise CampaignError(f"{src}: expected a folder of scan files or an .e57 file")
    folder = Path(out).expanduser() if out is not None else (src.parent if src.is_file() else src)
    folder.mkdir(parents=True, exist_ok=True)
    manifest = folder / MANIFEST
    if manifest.exists() and not force:
        raise CampaignError(f"{manifest}: already exists (--force replaces it)")
    found = find_scans(src, folder)
    if not found:
        raise CampaignError(f"{src}: no scan files ({' '.join(SCAN_EXTENSIONS)})")
    from forestmap_assets.io.writers import atomic_write

    with atomic_write(manifest) as tmp:
        tmp.write_text(manifest_text(folder.resolve().name, found))
    return manifest, found
