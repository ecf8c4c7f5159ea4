"""Damaged scan files are refused, not read in part (issue 18): a truncated PLY, PCD, LAS/LAZ
or text file, or one whose header gives a wrong point count, raises one :class:`ScanReadError`
line naming the file and comparing the header's point count with what the file holds."""

from __future__ import annotations

import re
import struct
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.io.readers import read_scan
from forestmap_assets.io.readers_common import ScanReadError
from forestmap_assets.io.writers import scan_points, write_scan


def _image(with_rgb: bool = False) -> RangeImage:
    """40 x 90 image on a 1 deg grid with holes; every border row/column holds a return."""
    rng = np.random.default_rng(7)
    r = rng.uniform(2.0, 25.0, (40, 90)).astype(np.float32)
    r[rng.random(r.shape) < 0.15] = np.nan
    r[0, :], r[-1, :], r[:, 0], r[:, -1] = 5.0, 6.0, 7.0, 8.0
    rgb = rng.integers(0, 256, (40, 90, 3)).astype(np.uint8) if with_rgb else None
    inten = rng.integers(0, 4000, r.shape).astype(np.float32)
    return RangeImage(r, -60.0 + np.arange(90.0), 20.0 - np.arange(40.0), intensity=inten, rgb=rgb)


IMAGE = _image()
N = int(IMAGE.valid.sum())


def _open3d_file(path: Path, **kw) -> Path:
    """PLY/PCD variants the project's writer does not make (ASCII, compressed)."""
    xyz, _ = scan_points(IMAGE)
    pc = o3d.t.geometry.PointCloud()
    pc.point.positions = o3d.core.Tensor(np.ascontiguousarray(xyz))
    assert o3d.t.io.write_point_cloud(str(path), pc, **kw)
    return path


MAKERS = {
    "binary.ply": lambda p: write_scan(p, IMAGE),
    "ascii.ply": lambda p: _open3d_file(p, write_ascii=True),
    "binary.pcd": lambda p: write_scan(p, IMAGE),
    "ascii.pcd": lambda p: _open3d_file(p, write_ascii=True),
    "compressed.pcd": lambda p: _open3d_file(p, compressed=True),
    "scan.las": lambda p: write_scan(p, IMAGE),
    "scan.laz": lambda p: write_scan(p, IMAGE),
}
LAS = "corrupt or truncated LAS/LAZ data"


def _one_line(info, path: Path) -> str:
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith(f"{path}: "), msg
    return msg


def _cut(src: Path, share: float) -> Path:
    data = src.read_bytes()
    dst = src.with_name(f"cut-{src.name}")
    dst.write_bytes(data[: int(len(data) * share)])
    return dst


@pytest.mark.parametrize("name", MAKERS)
def test_valid_files_still_read(tmp_path, name):
    path = MAKERS[name](tmp_path / name)
    assert int(read_scan(path).valid.sum()) == N


@pytest.mark.parametrize("name", ["binary.ply", "ascii.ply", "binary.pcd", "ascii.pcd", "scan.las"])
@pytest.mark.parametrize("share", [0.6, 0.999])
def test_truncated_file_names_header_count_and_points_held(tmp_path, name, share):
    cut = _cut(MAKERS[name](tmp_path / name), share)
    with pytest.raises(ScanReadError) as info:
        read_scan(cut)
    msg = _one_line(info, cut)
    found = re.search(r"truncated: header says (\d+) points, file holds (\d+)", msg)
    assert found, msg
    said, held = int(found[1]), int(found[2])
    assert said == N and 0 < held < N
    if share == 0.6:
        assert abs(held - 0.6 * N) < 0.05 * N  # (nearly) the share of the points the cut kept
    else:
        assert held > 0.99 * N
    assert name != "scan.las" or LAS in msg


def test_truncated_laz_and_compressed_pcd(tmp_path):
    laz = _cut(MAKERS["scan.laz"](tmp_path / "scan.laz"), 0.6)
    with pytest.raises(ScanReadError) as info:
        read_scan(laz)
    msg = _one_line(info, laz)
    assert LAS in msg and f"truncated: header says {N} points, file holds about " in msg
    about = int(re.search(r"holds about (\d+)", msg)[1])
    assert 0.4 * N < about < 0.8 * N  # compressed: an estimate, said so
    pcd = _cut(MAKERS["compressed.pcd"](tmp_path / "compressed.pcd"), 0.6)
    with pytest.raises(ScanReadError) as info:
        read_scan(pcd)
    assert re.search(rf"truncated: header says {N} points, file holds \d+ of their \d+ compressed bytes$",
                     _one_line(info, pcd))


def _set_count(path: Path, count: int) -> Path:
    """A copy of the file whose header gives ``count`` points."""
    data = path.read_bytes()
    if path.suffix in (".las", ".laz"):
        data = data[:107] + struct.pack("<I", count) + data[111:]
    elif path.suffix == ".ply":
        data = re.sub(rb"element vertex \d+", b"element vertex %d" % count, data, count=1)
    else:
        data = re.sub(rb"\nWIDTH \d+", b"\nWIDTH %d" % count, data, count=1)
        data = re.sub(rb"\nPOINTS \d+", b"\nPOINTS %d" % count, data, count=1)
    out = path.with_name(f"count{count}-{path.name}")
    out.write_bytes(data)
    return out


@pytest.mark.parametrize("name", ["binary.ply", "ascii.ply", "binary.pcd", "ascii.pcd", "scan.las"])
@pytest.mark.parametrize("delta", [500, -500])
def test_wrong_header_count(tmp_path, name, delta):
    bad = _set_count(MAKERS[name](tmp_path / name), N + delta)
    with pytest.raises(ScanReadError) as info:
        read_scan(bad)
    kind = "truncated" if delta > 0 else "damaged"
    assert f"{kind}: header says {N + delta} points, file holds {N}" in _one_line(info, bad)


def test_laz_with_a_larger_header_count_and_pcd_header_at_odds(tmp_path):
    laz = _set_count(MAKERS["scan.laz"](tmp_path / "scan.laz"), N + 500)
    with pytest.raises(ScanReadError) as info:
        read_scan(laz)
    assert f"{LAS} (header says {N + 500} points; " in _one_line(info, laz)
    pcd = MAKERS["binary.pcd"](tmp_path / "binary.pcd")
    odd = tmp_path / "odd.pcd"
    odd.write_bytes(re.sub(rb"\nPOINTS \d+", b"\nPOINTS 12", pcd.read_bytes(), count=1))
    with pytest.raises(ScanReadError) as info:
        read_scan(odd)
    assert f"damaged PCD header (POINTS 12, but WIDTH x HEIGHT = {N} x 1)" in _one_line(info, odd)


def test_ply_with_faces_after_the_vertices_reads(tmp_path):
    """A mesh PLY (vertices, then faces with a list property) is not taken for a damaged file."""
    xyz, _ = scan_points(IMAGE)
    header = (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {len(xyz)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "element face 2\nproperty list uchar int vertex_indices\nend_header\n"
    ).encode()
    faces = b"".join(b"\x03" + np.array(f, "<i4").tobytes() for f in ([0, 1, 2], [1, 2, 3]))
    path = tmp_path / "mesh.ply"
    path.write_bytes(header + xyz.astype("<f4").tobytes() + faces)
    assert int(read_scan(path).valid.sum()) == N
    cut = _cut(path, 0.5)
    with pytest.raises(ScanReadError, match=rf"truncated: header says {N} points, file holds \d+$"):
        read_scan(cut)


def test_damaged_ply_header(tmp_path):
    path = tmp_path / "h.ply"
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty float x\n")
    with pytest.raises(ScanReadError, match="h.ply: damaged PLY header \\(no end_header line\\)$"):
        read_scan(path)
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 5x\nend_header\n")
    with pytest.raises(ScanReadError, match="damaged PLY header \\(line 'element vertex 5x'\\)$"):
        read_scan(path)


@pytest.mark.parametrize("name", ["scan.xyz", "scan.csv"])
def test_text_cut_inside_its_last_line(tmp_path, name):
    path = write_scan(tmp_path / name, _image(with_rgb=True))
    lines = path.read_text().splitlines()
    sep = "," if name.endswith(".csv") else " "
    cut = tmp_path / f"cut-{name}"
    cut.write_text("\n".join([*lines[:-1], sep.join(lines[-1].split(sep)[:2])]))  # no final newline
    with pytest.raises(ScanReadError) as info:
        read_scan(cut)
    msg = _one_line(info, cut)
    assert msg.endswith(f"truncated: the last line ({len(lines)}) holds 2 of {len(lines[-1].split(sep))} values")
    cut.write_text("\n".join(lines[:-1]) + "\n")  # cut at a line break: a shorter, valid file
    assert int(read_scan(cut).valid.sum()) == N - 1


@pytest.mark.slow
def test_run_leaves_a_damaged_scan_out_and_exits_3(tmp_path, capsys):
    """``forestmap run`` with a truncated PLY: the other scans and the campaign-level stages go
    on, the outputs are written, the exit code is 3 and standard error names scan and file."""
    from helpers.campaign_files import write_campaign, write_npz_scan

    from forestmap_assets.cli import main

    root = write_campaign(tmp_path / "plot", scans=("T", "S"))
    ply = write_scan(root / "scans" / "R.ply", read_scan(write_npz_scan(tmp_path / "r.npz", seed=5)))
    ply.write_bytes(ply.read_bytes()[: int(ply.stat().st_size * 0.6)])
    with open(root / "campaign.yaml", "a") as f:
        f.write("  - {id: R, path: scans/R.ply}\n")
    capsys.readouterr()
    assert main(["run", str(root), "--no-report", "--no-cloud"]) == 3
    out, err = capsys.readouterr()
    said = rf"{re.escape(str(ply))}: truncated: header says \d+ points, file holds \d+"
    assert re.fullmatch(rf"forestmap: scan R left out of the outputs: {said}\n", err), err
    assert "outputs written to" in out and (root / "outputs" / "poses.csv").exists()

    # a damaged file in place of a scan processed before: its earlier results stand, said so
    (root / "scans" / "S.npz").write_bytes(b"PK\x03\x04 cut short")
    assert main(["run", str(root), "--no-report", "--no-cloud"]) == 3
    err = capsys.readouterr().err
    assert err.startswith("forestmap: scan S not updated (outputs use its earlier results): "), err
    assert "S.npz: " in err and err.endswith(" (also left out: R)\n") and err.count("\n") == 1
