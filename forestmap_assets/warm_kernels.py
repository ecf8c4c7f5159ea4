"""Compile forestmap's numba kernels into their on-disk cache once, at install (issue 16).

Every kernel is ``@njit(cache=True)``: a process loads it from ``__pycache__`` instead of
compiling it, but only once some process has compiled it on this machine. Without this step
that is the user's first ``forestmap run``, which then takes several minutes longer (about 150 s
of compiling on a 2-core machine: the branch-and-bound search alone 90 s). ``scripts/setup.sh``
runs this module after installing: it simulates a small campaign (three quarter-resolution
scans of realistic stems, no prior; two unorganised PLY clouds without a sensor step, which take
the projection path with its step estimate, and one organised npz range image) in a temporary
folder and runs the whole pipeline on it with a temporary home, then a full-turn LAZ scan and
two fine PLY clouds as other tools write them (:func:`full_turn_campaign`,
:func:`fine_ply_campaign`), so every stage's kernels are compiled with the argument types a real
run gives them. Nothing outside the temporary folder is written but the kernel cache and a stamp
beside it: the fingerprint of the kernels' sources, so that the next set-up skips this step
until a kernel changes.

    python -m forestmap_assets.warm_kernels [--force | --check]   # about 2-3 min on 2 cores, once
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

SCANS = ("T", "S", "R")
ORGANISED = "R"  # this scan stays an npz range image; the others are unorganised PLY


def _forestmap(args: list[str], env: dict[str, str]) -> None:
    cmd = [sys.executable, "-m", "forestmap_assets.cli", "--quiet", *args]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        why = (done.stderr.strip().splitlines() or ["no message"])[-1]
        raise RuntimeError(f"forestmap {args[0]} exited {done.returncode}: {why}")


def warm_campaign(root: Path, env: dict[str, str]) -> Path:
    """A 3-scan campaign in ``root/campaign``: PLY scans without a sensor step, one npz scan."""
    common = ["--scans", str(len(SCANS)), "--trees", "30", "--plot-size", "30", "--seed", "7",
              "--resolution", "quarter", "--no-prior", "--stems", "realistic"]
    camp, npz = root / "campaign", root / "npz"
    _forestmap(["simulate", str(camp), *common, "--format", "ply"], env)
    _forestmap(["simulate", str(npz), *common, "--format", "npz"], env)
    (camp / "scans" / f"{ORGANISED}.ply").unlink()
    (npz / "scans" / f"{ORGANISED}.npz").rename(camp / "scans" / f"{ORGANISED}.npz")
    doc = {"name": "warm-kernels", "environment": "forest",
           "scans": [{"id": s, "path": f"scans/{s}.{'npz' if s == ORGANISED else 'ply'}"}
                     for s in SCANS]}
    (camp / "campaign.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    return camp


def full_turn_campaign(root: Path) -> Path:
    """A one-scan campaign in ``root/full_turn``: a 360 x 100 deg LAZ cloud as a terrestrial
    scanner's software exports it (0.1 mm integer coordinates, 16-bit intensity, 10 % of the
    returns lost), its beams jittered so that no 0.01 deg of azimuth is empty (the dense full
    circle's seam search) and over 200 k points (the step estimate's window subset)."""
    import laspy
    import numpy as np

    from forestmap_assets.sim.forest import make_forest
    from forestmap_assets.sim.scanner import ScanPose, VirtualScanner

    world = make_forest(12, 20.0, n_scans=1, seed=np.random.default_rng(7))
    x, y = (float(v) for v in world.scan_xy[0])
    z = float(world.ground.height(np.array([x]), np.array([y]))[0]) + 1.5
    scanner = VirtualScanner(world, hfov_deg=360.0, vfov_deg=100.0, n_cols=1800, n_rows=500)
    xyz, inten = scanner.scan_points(ScanPose(x, y, z), seed=7, jitter_steps=0.5, dropout=0.1)
    camp = root / "full_turn"
    camp.mkdir()
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales, header.offsets = np.full(3, 1e-4), np.zeros(3)
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.intensity = np.clip(np.rint(inten * 65535), 0, 65535).astype(np.uint16)
    las.write(str(camp / "A.laz"), do_compress=True)
    doc = {"name": "warm-kernels-full-turn", "environment": "forest",
           "scans": [{"id": "A", "path": "A.laz"}]}
    (camp / "campaign.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    return camp


def fine_ply_campaign(root: Path) -> Path:
    """A two-scan campaign in ``root/fine_ply``: unorganised PLY clouds at 0.1 deg without
    intensity, as other tools write them: ``D`` with float64 coordinates (Sylva's simulator),
    ``F`` with float32 coordinates and RGB (clouds rendered from a registered TLS cloud). Their
    rows are finer than the segments' ``min_line_step_deg``, so the segments see every second
    row (writable copies, not the stored table's read-only columns): the kernels' argument types
    the quarter-resolution campaign does not give (a first run on Sylva's or rendered scans
    otherwise compiled five kernels, 1-2 s in each worker)."""
    import numpy as np

    from forestmap_assets.sim.cloud_render import write_ply_xyz
    from forestmap_assets.sim.forest import make_forest
    from forestmap_assets.sim.scanner import ScanPose, VirtualScanner

    world = make_forest(12, 20.0, n_scans=2, seed=np.random.default_rng(8))
    camp = root / "fine_ply"
    camp.mkdir()
    scanner = VirtualScanner(world, hfov_deg=360.0, vfov_deg=40.0, n_cols=3600, n_rows=400)
    for i, sid in enumerate(("D", "F")):
        x, y = (float(v) for v in world.scan_xy[i])
        z = float(world.ground.height(np.array([x]), np.array([y]))[0]) + 1.5
        xyz, _ = scanner.scan_points(ScanPose(x, y, z, heading_deg=40.0 * i), seed=i, jitter_steps=0.3)
        rgb = None if sid == "D" else np.full((len(xyz), 3), 128, np.uint8)
        write_ply_xyz(camp / f"{sid}.ply", xyz, rgb, double=sid == "D")
    doc = {"name": "warm-kernels-fine-ply", "environment": "forest",
           "scans": [{"id": s, "path": f"{s}.ply"} for s in ("D", "F")]}
    (camp / "campaign.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    return camp


def fingerprint() -> str:
    """The kernels' sources, numba's version and the cache folder, hashed."""
    import numba

    h = hashlib.sha256(f"{numba.__version__} {sys.version} {os.environ.get('NUMBA_CACHE_DIR', '')}".encode())
    for path in sorted(Path(__file__).parent.rglob("*.py")):
        text = path.read_bytes()
        if b"njit" in text:
            h.update(path.relative_to(Path(__file__).parent).as_posix().encode() + text)
    return h.hexdigest()


def stamp_file() -> Path:
    return Path(__file__).parent / "__pycache__" / "warm_kernels.stamp"


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    stamp, mark = stamp_file(), fingerprint()
    current = stamp.exists() and stamp.read_text() == mark
    if "--check" in args:  # exit 0 when the cache is current, 1 when it is not
        return 0 if current else 1
    if current and "--force" not in args:
        print("warm_kernels: the kernel cache is up to date")
        return 0
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="forestmap-warm-") as tmp:
        root = Path(tmp)
        env = {**os.environ, "FORESTMAP_HOME": str(root / "home")}
        try:
            _forestmap(["run", str(warm_campaign(root, env))], env)
            _forestmap(["run", str(full_turn_campaign(root)), "--no-cloud"], env)
            _forestmap(["run", str(fine_ply_campaign(root)), "--no-cloud"], env)
        except RuntimeError as exc:
            print(f"warm_kernels: {exc}; the first run will compile what is missing", file=sys.stderr)
            return 1
    stamp.parent.mkdir(exist_ok=True)
    stamp.write_text(mark)
    print(f"warm_kernels: kernels compiled and cached in {time.perf_counter() - started:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
