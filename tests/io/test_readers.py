"""Scan readers and writers: every format round-trips (DESIGN section 2, spec 1.2)."""

from __future__ import annotations

import os
from pathlib import Path

import laspy
import numpy as np
import pye57
import pytest
from scipy.spatial import cKDTree

from forestmap_assets.core.features.range_image import RangeImage, spherical_to_xyz
from forestmap_assets.io.readers import SCAN_EXTENSIONS, read_scan
from forestmap_assets.io.readers_common import ScanReadError
from forestmap_assets.io.writers import atomic_write, scan_points, write_scan

ORGANISED = ("npz", "e57")
UNORGANISED = ("las", "laz", "ply", "pcd", "xyz", "txt", "csv")
KEEPS_INTENSITY = ("npz", "e57", "las", "laz", "ply", "pcd", "csv")


def synthetic_image(*, with_rgb: bool, seed: int = 0, tilt=(0.0, 0.0)) -> RangeImage:
    """40 x 90 organised image on a 1 deg grid, NaN holes inside, full border rows/columns."""
    rng = np.random.default_rng(seed)
    rows, cols = 40, 90
    az = -60.0 + 1.0 * np.arange(cols)
    el = 20.0 - 1.0 * np.arange(rows)
    r = rng.uniform(2.0, 25.0, (rows, cols)).astype(np.float32)
    r[rng.random((rows, cols)) < 0.15] = np.nan
    r[0, :], r[-1, :], r[:, 0], r[:, -1] = 5.0, 6.0, 7.0, 8.0
    rgb = rng.integers(0, 256, (rows, cols, 3)).astype(np.uint8) if with_rgb else None
    inten = rng.integers(0, 4000, (rows, cols)).astype(np.float32)
    return RangeImage(r, az, el, tilt_deg=tilt, intensity=inten, rgb=rgb)


def sensor_points(img: RangeImage) -> np.ndarray:
    return spherical_to_xyz(img.range_m, img.azimuth_deg, img.elevation_deg)[img.valid]


def assert_same_point_set(a: np.ndarray, b: np.ndarray, tol: float = 1e-5) -> None:
    assert a.shape == b.shape
    assert cKDTree(b).query(a)[0].max() < tol
    assert cKDTree(a).query(b)[0].max() < tol


@pytest.mark.parametrize("with_rgb", [True, False], ids=["rgb", "no-rgb"])
@pytest.mark.parametrize("ext", ORGANISED + UNORGANISED)
def test_round_trip_every_format(tmp_path, ext, with_rgb):
    img = synthetic_image(with_rgb=with_rgb)
    path = write_scan(tmp_path / f"scan.{ext}", img)
    assert path.exists() and path.stat().st_size > 0
    assert [p.name for p in tmp_path.iterdir()] == [f"scan.{ext}"]  # no temp files left
    back = read_scan(path)
    # same points in the scanner frame (as sets, which is all an unorganised file keeps)
    assert_same_point_set(sensor_points(back), sensor_points(img))
    # ... and the organised image itself: same grid, same ranges at the same pixels
    assert back.shape == img.shape
    np.testing.assert_array_equal(back.valid, img.valid)
    np.testing.assert_allclose(back.range_m[img.valid], img.range_m[img.valid], rtol=1e-6)
    np.testing.assert_allclose(back.azimuth_deg, img.azimuth_deg, atol=1e-6)
    np.testing.assert_allclose(back.elevation_deg, img.elevation_deg, atol=1e-6)
    if ext in ORGANISED:
        np.testing.assert_array_equal(back.range_m[img.valid], img.range_m[img.valid])
    if with_rgb:
        assert back.rgb is not None
        np.testing.assert_array_equal(back.rgb[img.valid], img.rgb[img.valid])
    else:
        assert back.rgb is None
    if ext in KEEPS_INTENSITY:
        np.testing.assert_allclose(back.intensity[img.valid], img.intensity[img.valid])


def test_points_written_in_scanner_frame_and_tilt_from_caller(tmp_path):
    img = synthetic_image(with_rgb=False, tilt=(4.0, -3.0))
    path = write_scan(tmp_path / "tilted.las", img)
    las = laspy.read(str(path))
    raw = np.column_stack([las.x, las.y, las.z])
    assert_same_point_set(raw, sensor_points(img))  # not the levelled img.xyz
    assert cKDTree(raw).query(img.xyz[img.valid])[0].max() > 0.1
    back = read_scan(path, tilt_deg=(4.0, -3.0))
    assert back.tilt_deg == (4.0, -3.0)
    np.testing.assert_allclose(back.xyz[img.valid], img.xyz[img.valid], atol=1e-5)
    assert read_scan(path).tilt_deg == (0.0, 0.0)


def test_scan_points_matches_spherical_to_xyz():
    img = synthetic_image(with_rgb=False)
    xyz, vu = scan_points(img)
    np.testing.assert_allclose(xyz, sensor_points(img))
    np.testing.assert_array_equal(vu, np.argwhere(img.valid))


def test_structured_e57_from_other_software(tmp_path):
    """Cartesian float32, rows bottom-up, columns clockwise, a scan pose: read in scan frame."""
    img = synthetic_image(with_rgb=True)
    v, u = np.nonzero(img.valid)
    p = sensor_points(img)
    rows, cols = img.shape
    data = {
        "cartesianX": p[:, 0],
        "cartesianY": p[:, 1],
        "cartesianZ": p[:, 2],
        "rowIndex": (rows - 1 - v).astype(np.uint16),
        "columnIndex": (cols - 1 - u).astype(np.uint16),
        "colorRed": img.rgb[v, u, 0],
        "colorGreen": img.rgb[v, u, 1],
        "colorBlue": img.rgb[v, u, 2],
    }
    path = tmp_path / "faro.e57"
    with pye57.E57(str(path), mode="w") as e57:
        e57.write_scan_raw(
            data,
            rotation=np.array([0.7071068, 0, 0, 0.7071068]),
            translation=np.array([10.0, 5.0, 1.0]),
        )
    back = read_scan(path)
    assert back.shape == img.shape
    np.testing.assert_array_equal(back.valid, img.valid)
    np.testing.assert_allclose(back.range_m[img.valid], img.range_m[img.valid], atol=1e-5)
    np.testing.assert_allclose(back.azimuth_deg, img.azimuth_deg, atol=1e-5)
    np.testing.assert_allclose(back.elevation_deg, img.elevation_deg, atol=1e-5)
    np.testing.assert_array_equal(back.rgb[img.valid], img.rgb[img.valid])


def test_unstructured_e57_is_projected_and_multi_scan_needs_index(tmp_path):
    img = synthetic_image(with_rgb=False)
    p = sensor_points(img)
    data = {"cartesianX": p[:, 0], "cartesianY": p[:, 1], "cartesianZ": p[:, 2]}
    one, two = tmp_path / "u.e57", tmp_path / "two.e57"
    with pye57.E57(str(one), mode="w") as e57:
        e57.write_scan_raw(data)
    back = read_scan(one)
    assert back.shape == img.shape
    np.testing.assert_allclose(back.range_m[img.valid], img.range_m[img.valid], atol=1e-5)
    with pye57.E57(str(two), mode="w") as e57:
        e57.write_scan_raw(data)
        e57.write_scan_raw({k: v[:500] for k, v in data.items()})
    with pytest.raises(ScanReadError, match="holds 2 scans"):
        read_scan(two)
    assert read_scan(two, scan_index=0).shape == img.shape
    assert read_scan(two, scan_index=1).valid.sum() == 500


def test_angular_step_given_for_unorganised_file(tmp_path):
    img = synthetic_image(with_rgb=False)
    path = write_scan(tmp_path / "s.ply", img)
    coarse = read_scan(path, angular_step_deg=2.0)
    assert coarse.shape == (20, 45)
    assert coarse.azimuth_step_deg == pytest.approx(2.0)
    assert read_scan(path, angular_step_deg=(1.0, 1.0)).shape == img.shape


def test_npz_orientation_normalised_and_rgb_kept(tmp_path):
    img = synthetic_image(with_rgb=True)
    path = tmp_path / "flipped.npz"
    np.savez(
        path,
        range=img.range_m[::-1, ::-1],
        azimuth_deg=img.azimuth_deg[::-1],
        elevation_deg=img.elevation_deg[::-1],
        rgb=img.rgb[::-1, ::-1],
    )
    back = read_scan(path)
    np.testing.assert_array_equal(back.azimuth_deg, img.azimuth_deg)
    np.testing.assert_array_equal(back.elevation_deg, img.elevation_deg)
    np.testing.assert_array_equal(back.range_m, img.range_m)
    np.testing.assert_array_equal(back.rgb, img.rgb)
    assert back.intensity is None


@pytest.mark.parametrize(
    "name, text",
    [
        ("c.csv", "x,y,z,red,green,blue\n{rows}"),
        ("w.xyz", "{rows}"),
        ("h.txt", "//X Y Z R G B\n{rows}"),
        ("t.txt", "\n{rows}"),
    ],
)
def test_text_variants(tmp_path, name, text):
    img = synthetic_image(with_rgb=True)
    p = sensor_points(img)
    c = img.rgb[img.valid]
    sep = "," if name.endswith(".csv") else ("\t" if name == "t.txt" else "  ")
    rows = "".join(
        sep.join([f"{a:.9f}" for a in pt] + [str(int(k)) for k in cc]) + "\n"
        for pt, cc in zip(p, c, strict=True)
    )
    path = tmp_path / name
    path.write_text(text.format(rows=rows))
    back = read_scan(path)
    assert back.shape == img.shape
    np.testing.assert_allclose(back.range_m[img.valid], img.range_m[img.valid], atol=1e-6)
    np.testing.assert_array_equal(back.rgb[img.valid], c)


def _ply(path: Path, fmt: str, xyz: np.ndarray, rgb: np.ndarray | None, coord: str) -> Path:
    """A PLY as other software writes it: ``fmt`` (ascii, binary_little_endian,
    binary_big_endian), ``coord`` float or double, CloudCompare-style scalar fields."""
    n = len(xyz)
    cols = [
        ("x", coord, xyz[:, 0]),
        ("y", coord, xyz[:, 1]),
        ("z", coord, xyz[:, 2]),
        ("scalar_Intensity", "float", np.linspace(0.0, 1.0, n)),
        ("scalar_Return_Number", "uchar", np.ones(n)),
    ]
    if rgb is not None:
        cols += [(c, "uchar", rgb[:, i]) for i, c in enumerate(("red", "green", "blue"))]
    head = f"ply\nformat {fmt} 1.0\ncomment other software\nelement vertex {n}\n"
    head += "".join(f"property {t} {name}\n" for name, t, _ in cols) + "end_header\n"
    if fmt == "ascii":
        rows = zip(
            *[[str(int(v)) if t == "uchar" else repr(float(v)) for v in a] for _, t, a in cols],
            strict=True,
        )
        path.write_text(head + "".join(" ".join(r) + "\n" for r in rows))
        return path
    order = ">" if fmt == "binary_big_endian" else "<"
    table = np.empty(
        n,
        [(name, order + {"float": "f4", "double": "f8", "uchar": "u1"}[t]) for name, t, _ in cols],
    )
    for name, _, a in cols:
        table[name] = a
    path.write_bytes(head.encode() + table.tobytes())
    return path


@pytest.mark.parametrize(
    "fmt, coord, with_rgb",
    [
        ("binary_little_endian", "double", True),
        ("binary_big_endian", "float", True),
        ("ascii", "float", True),
        ("binary_little_endian", "double", False),
    ],
)
def test_ply_variants_of_other_software(tmp_path, fmt, coord, with_rgb):
    img = synthetic_image(with_rgb=True)
    p = sensor_points(img).astype(np.float32).astype(np.float64)  # exact in both widths
    rgb = img.rgb[img.valid] if with_rgb else None
    back = read_scan(_ply(tmp_path / "s.ply", fmt, p, rgb, coord))
    assert back.shape == img.shape
    np.testing.assert_array_equal(back.valid, img.valid)
    assert_same_point_set(sensor_points(back), p)
    if with_rgb:
        np.testing.assert_array_equal(back.rgb[img.valid], rgb)
    else:
        assert back.rgb is None


def test_text_colours_in_unit_range_and_las_8bit_colours(tmp_path):
    img = synthetic_image(with_rgb=True)
    p, c = sensor_points(img), img.rgb[img.valid]
    unit = np.column_stack([p, c / 255.0])
    np.savetxt(tmp_path / "u.xyz", unit, fmt="%.9f")
    np.testing.assert_array_equal(read_scan(tmp_path / "u.xyz").rgb[img.valid], c)
    las = laspy.create(point_format=2, file_version="1.2")
    las.header.scales = np.array([1e-6] * 3)
    las.header.offsets = np.zeros(3)
    las.x, las.y, las.z = p[:, 0], p[:, 1], p[:, 2]
    las.red, las.green, las.blue = (c[:, i].astype(np.uint16) for i in range(3))  # 8-bit values
    las.write(str(tmp_path / "eight.las"))
    np.testing.assert_array_equal(read_scan(tmp_path / "eight.las").rgb[img.valid], c)


def test_atomic_write_renames_on_success_and_cleans_up_on_failure(tmp_path):
    target = tmp_path / "sub" / "out.npz"
    with atomic_write(target) as tmp:
        assert tmp.parent == target.parent and tmp.suffix == ".npz" and tmp != target
        tmp.write_bytes(b"first")
        assert not target.exists()
    assert target.read_bytes() == b"first"
    with pytest.raises(RuntimeError), atomic_write(target) as tmp:
        tmp.write_bytes(b"half")
        raise RuntimeError("boom")
    assert target.read_bytes() == b"first"
    assert sorted(p.name for p in target.parent.iterdir()) == ["out.npz"]
    with pytest.raises(ValueError, match="unsupported extension '.foo'"):
        write_scan(tmp_path / "x.foo", synthetic_image(with_rgb=False))


# ---- bad input: one line, naming the file and the reason --------------------------------------


def _npz(**arrays):
    def make(path: Path) -> None:
        with open(path, "wb") as f:
            np.savez(f, **arrays)

    return make


_GOOD = {"range": np.ones((4, 5)), "azimuth_deg": np.arange(5.0), "elevation_deg": -np.arange(4.0)}


def _trunc(ext: str):
    def make(path: Path) -> None:
        full = path.with_name("full" + path.suffix)
        write_scan(full, synthetic_image(with_rgb=False))
        data = full.read_bytes()
        path.write_bytes(data[: len(data) // 3])

    return make


BAD_CASES = [
    (
        "T.npz",
        _npz(azimuth_deg=np.arange(5.0), elevation_deg=np.arange(4.0)),
        "missing array 'range'",
    ),
    (
        "T.npz",
        _npz(**{**_GOOD, "azimuth_deg": np.arange(7.0)}),
        "array 'azimuth_deg' has shape (7,), expected (5,)",
    ),
    ("T.npz", _npz(**{**_GOOD, "range": np.ones(20)}), "array 'range' must be 2-D"),
    ("T.npz", _npz(**{**_GOOD, "rgb": np.zeros((4, 5), np.uint8)}), "array 'rgb' has shape"),
    (
        "T.npz",
        _npz(**{**_GOOD, "range": np.array([["a"] * 5] * 4)}),
        "array 'range' is not numeric",
    ),
    (
        "T.npz",
        _npz(**{**_GOOD, "azimuth_deg": np.array([0.0, 2, 1, 3, 4])}),
        "not strictly monotonic",
    ),
    ("T.npz", lambda p: p.write_text("range,1,2\n"), "not an NPZ archive (bad signature)"),
    (
        "S.las",
        lambda p: p.write_bytes(b"PK not a las file at all"),
        "not a LAS file (bad signature)",
    ),
    ("S.laz", lambda p: p.write_bytes(b"\x00" * 400), "not a LAS file (bad signature)"),
    ("S.las", _trunc("las"), "corrupt or truncated LAS/LAZ data"),
    ("S.laz", _trunc("laz"), "corrupt or truncated LAS/LAZ data"),
    ("x.foo", lambda p: p.write_text("1 2 3\n"), "unsupported extension '.foo'"),
    ("noext", lambda p: p.write_text("1 2 3\n"), "no file extension"),
    ("c.xyz", lambda p: p.write_text("1 2 3\n4 5 6\nabc 1 2\n"), "line 3: non-numeric value 'abc'"),
    ("c.csv", lambda p: p.write_text("x,y\n1,2\n3,4\n"), "expected at least 3 columns"),
    ("c.txt", lambda p: p.write_text("x y z\n"), "no points"),
    ("c.xyz", lambda p: p.write_text("1 2 3\n4 5\n"), "line 2: missing or non-finite x/y/z"),
    ("c.xyz", lambda p: p.write_text("1 2 3\n4 5 6 7\n"), "malformed text"),
    ("c.txt", lambda p: p.write_bytes(b"\x00\x01\x02\x03"), "binary data"),
    ("p.ply", lambda p: p.write_text("not a ply\n"), "not a PLY file (bad signature)"),
    ("q.pcd", lambda p: p.write_text("garbage\n"), "not a PCD file"),
    ("e.e57", lambda p: p.write_bytes(b"PK\x03\x04"), "not an E57 file (bad signature)"),
    ("e.e57", _trunc("e57"), "e.e57: E57Exception"),
    ("d.npz", lambda p: p.mkdir(), "is a directory"),
] + [(f"empty.{ext[1:]}", lambda p: p.write_bytes(b""), "empty file") for ext in SCAN_EXTENSIONS]


@pytest.mark.parametrize(
    "name, make, reason", BAD_CASES, ids=[f"{n}:{r[:24]}" for n, _, r in BAD_CASES]
)
def test_bad_input_gives_one_line_error_naming_file(tmp_path, name, make, reason):
    path = tmp_path / name
    make(path)
    with pytest.raises(ScanReadError) as info:
        read_scan(path)
    msg = str(info.value)
    assert isinstance(info.value, ValueError)
    assert "\n" not in msg
    assert msg.startswith(f"{path}: ")
    assert reason in msg


def test_missing_file_and_bad_tilt(tmp_path):
    with pytest.raises(ScanReadError, match=r"scans/none\.npz: file not found$"):
        read_scan("scans/none.npz")
    path = write_scan(tmp_path / "s.npz", synthetic_image(with_rgb=False))
    with pytest.raises(ScanReadError, match="tilt_deg"):
        read_scan(path, tilt_deg=(1.0,))
    os.chmod(path, 0o644)
