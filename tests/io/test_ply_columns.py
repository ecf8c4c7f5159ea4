"""The binary PLY reader (io/readers_clouds.py): the vertex rows mapped from the file give what
Open3D's reader gives (points, colour, intensity) on the types Open3D reads, in either byte
order, and also the 16-bit colours and intensities Open3D skips."""

import numpy as np
import pytest

from forestmap_assets.io import readers_clouds as rc

NUMPY_TO_PLY = {"f4": "float", "f8": "double", "u1": "uchar", "u2": "ushort"}


def _write(path, fmt, fields, n=500, seed=0):
    rng = np.random.default_rng(seed)
    order = ">" if fmt == "binary_big_endian" else "<"
    rows = np.zeros(n, np.dtype([(name, order + t) for name, t in fields]))
    for name, t in fields:
        if t.startswith("f"):
            rows[name] = rng.uniform(-20, 20, n) if name in "xyz" else rng.uniform(0, 1, n)
        else:
            rows[name] = rng.integers(0, np.iinfo(np.dtype(t)).max + 1, n)
    head = f"ply\nformat {fmt} 1.0\nelement vertex {n}\n"
    head += "".join(f"property {NUMPY_TO_PLY[t]} {name}\n" for name, t in fields) + "end_header\n"
    path.write_bytes(head.encode() + rows.tobytes())
    return rows


def _open3d(path):
    import open3d as o3d

    pc = o3d.t.io.read_point_cloud(str(path))
    rgb = None
    if "colors" in pc.point:
        c = pc.point.colors.numpy()
        rgb = c.astype(np.uint8) if c.dtype == np.uint8 else rc.to_rgb8(c)
    intensity = pc.point.intensity.numpy().reshape(-1).astype(np.float32) if "intensity" in pc.point else None
    return pc.point.positions.numpy().astype(np.float64), rgb, intensity


XYZ = [("x", "f4"), ("y", "f4"), ("z", "f4")]


@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian"])
@pytest.mark.parametrize("fields", [
    XYZ,
    [("x", "f8"), ("y", "f8"), ("z", "f8"), ("intensity", "f4")],
    XYZ + [("red", "u1"), ("green", "u1"), ("blue", "u1")],
    XYZ + [("red", "f4"), ("green", "f4"), ("blue", "f4")],
], ids=["float", "double+intensity", "uchar colour", "float colour"])
def test_binary_ply_columns_match_open3d(tmp_path, fmt, fields):
    path = tmp_path / "scan.ply"
    _write(path, fmt, fields)
    got = rc._ply_columns(rc._binary_ply_vertices(path))
    for a, b in zip(_open3d(path), got, strict=True):
        assert (a is None) == (b is None)
        if a is not None:
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(a, b)


def test_sixteen_bit_colour_and_intensity_are_read(tmp_path):
    path = tmp_path / "scan.ply"
    rows = _write(path, "binary_little_endian",
                  XYZ + [("red", "u2"), ("green", "u2"), ("blue", "u2"), ("intensity", "u2")])
    xyz, rgb, intensity = rc._ply_columns(rc._binary_ply_vertices(path))
    assert rgb is not None and rgb.dtype == np.uint8 and rgb.shape == (len(rows), 3)
    assert np.corrcoef(rgb[:, 0].astype(float), rows["red"].astype(float))[0, 1] > 0.99
    np.testing.assert_array_equal(intensity, rows["intensity"].astype(np.float32))


def test_ascii_and_list_properties_go_to_open3d(tmp_path):
    ascii_ply = tmp_path / "a.ply"
    ascii_ply.write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                         "property float z\nend_header\n0 0 1\n1 0 1\n")
    assert rc._binary_ply_vertices(ascii_ply) is None
    mesh = tmp_path / "m.ply"
    mesh.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement face 1\nproperty list uchar int "
                     b"vertex_indices\nelement vertex 1\nproperty float x\nproperty float y\n"
                     b"property float z\nend_header\n" + bytes(1 + 12) + np.zeros(3, "<f4").tobytes())
    assert rc._binary_ply_vertices(mesh) is None
