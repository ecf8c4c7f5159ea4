"""Organised range images and levelling (spec 1.2).

A range image has ``rows x cols`` pixels; row ``v`` is a horizontal scan line at elevation
``elevation_deg[v]`` (row 0 at the top, elevations decreasing), column ``u`` is at azimuth
``azimuth_deg[u]`` (increasing). Sensor-frame point of a pixel:
``x = r cos(el) cos(az), y = r cos(el) sin(az), z = r sin(el)``; an image projected from an
unorganised cloud (io/projection.py) carries instead each pixel's own point (``points``): its
direction lies anywhere within (or, moved, next to) the pixel, and a point re-synthesised at the
pixel's centre would be up to half a pixel off (a stem then widens by a pixel and its circle
centre moves away from the scanner, issue 18).

Levelling: the scanner reports its measured ``roll`` (about x) and ``pitch`` (about y). A point
in the scanner's own frame ``p_s`` is rotated into the horizontally levelled sub-map frame by
``p = R_y(pitch) @ R_x(roll) @ p_s`` (origin kept at the sensor, z up).
"""

from __future__ import annotations

import functools
import json
import weakref
from dataclasses import dataclass, field

import numpy as np
import pyarrow as pa


def levelling_rotation(roll_deg: float, pitch_deg: float) -> np.ndarray:
    """Rotation taking scanner-frame vectors into the levelled frame, ``R_y(pitch) R_x(roll)``."""
    r, p = np.radians([roll_deg, pitch_deg])
    rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    return ry @ rx


# The last image decoded from a table, while that table lives: every per-scan stage of one scan's
# run decodes the same stored range image (the store hands the same table over, io/store.py).
_DECODED: list = []


def _forget_decoded(ref: weakref.ref) -> None:
    if _DECODED and _DECODED[0][0] is ref:
        _DECODED.clear()


def table_azimuth_step(table: pa.Table) -> tuple[float, int, int]:
    """Azimuth step (rad; NaN with fewer than 2 columns), column count and column direction (+1:
    azimuth grows with the column) of a stored range image (its ``azimuth_deg`` metadata)."""
    return _azimuth_step((table.schema.metadata or {})[b"azimuth_deg"])


@functools.lru_cache(maxsize=32)
def _azimuth_step(azimuth_json: bytes) -> tuple[float, int, int]:
    """:func:`table_azimuth_step` of the metadata's text, parsed once (the tree list asks each
    scan's image once a pass and stem: 1 ms of JSON a time for a 4,800-column image)."""
    az = np.asarray(json.loads(azimuth_json), np.float64)
    if az.size < 2:
        return float("nan"), int(az.size), 1
    return float(np.radians(np.median(np.abs(np.diff(az))))), int(az.size), 1 if az[-1] >= az[0] else -1


def table_points(table: pa.Table) -> np.ndarray:
    """The levelled points (n, 3) float64 of a stored range image, one row per valid pixel in
    the image's row-major order (its ``x, y, z`` columns)."""
    xyz = np.empty((table.num_rows, 3))
    for i, c in enumerate("xyz"):
        xyz[:, i] = table.column(c).to_numpy()
    return xyz


def spherical_to_xyz(range_m: np.ndarray, azimuth_deg: np.ndarray, elevation_deg: np.ndarray) -> np.ndarray:
    """Sensor-frame points (rows, cols, 3) of an organised range image; NaN where no return."""
    az = np.radians(np.asarray(azimuth_deg, dtype=np.float64))[None, :]
    el = np.radians(np.asarray(elevation_deg, dtype=np.float64))[:, None]
    r = np.asarray(range_m, dtype=np.float64)
    ce = np.cos(el)
    return np.stack([r * ce * np.cos(az), r * ce * np.sin(az), r * np.sin(el) * np.ones_like(az)], axis=-1)


@dataclass
class RangeImage:
    """An organised range image in the scanner's frame plus its measured tilt.

    ``range_m`` (rows, cols) float32 with NaN for no return; ``azimuth_deg`` (cols,),
    ``elevation_deg`` (rows,); optional ``intensity`` (rows, cols) float32 and ``rgb``
    (rows, cols, 3) uint8; optional ``points`` (rows, cols, 3) float32: the scanner-frame
    point of each pixel's return (NaN where none; ``range_m`` is its distance) when the pixel's
    centre is not that point's direction. ``xyz`` gives the levelled points.
    """

    range_m: np.ndarray
    azimuth_deg: np.ndarray
    elevation_deg: np.ndarray
    tilt_deg: tuple[float, float] = (0.0, 0.0)
    intensity: np.ndarray | None = None
    rgb: np.ndarray | None = None
    points: np.ndarray | None = field(default=None, repr=False)
    _xyz: np.ndarray | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.range_m = np.asarray(self.range_m, dtype=np.float32)
        self.azimuth_deg = np.asarray(self.azimuth_deg, dtype=np.float64)
        self.elevation_deg = np.asarray(self.elevation_deg, dtype=np.float64)
        if self.range_m.ndim != 2:
            raise ValueError(f"range: expected a 2-D array, got shape {self.range_m.shape}")
        rows, cols = self.range_m.shape
        if self.azimuth_deg.shape != (cols,):
            raise ValueError(f"azimuth_deg: expected {cols} values, got {self.azimuth_deg.shape}")
        if self.elevation_deg.shape != (rows,):
            raise ValueError(f"elevation_deg: expected {rows} values, got {self.elevation_deg.shape}")
        bad = np.isinf(self.range_m) | (self.range_m <= 0)  # NaN is already "no return"
        if bad.any():
            self.range_m = np.where(bad, np.float32(np.nan), self.range_m)
        if self.rgb is not None:
            self.rgb = np.asarray(self.rgb, dtype=np.uint8)
            if self.rgb.shape != (rows, cols, 3):
                raise ValueError(f"rgb: expected shape {(rows, cols, 3)}, got {self.rgb.shape}")
        if self.intensity is not None:
            self.intensity = np.asarray(self.intensity, dtype=np.float32)
            if self.intensity.shape != (rows, cols):
                raise ValueError(f"intensity: expected shape {(rows, cols)}, got {self.intensity.shape}")
        if self.points is not None:
            self.points = np.asarray(self.points, dtype=np.float32)
            if self.points.shape != (rows, cols, 3):
                raise ValueError(f"points: expected shape {(rows, cols, 3)}, got {self.points.shape}")

    @property
    def shape(self) -> tuple[int, int]:
        return self.range_m.shape

    @property
    def valid(self) -> np.ndarray:
        """Boolean mask of pixels with a return."""
        return np.isfinite(self.range_m)

    @property
    def azimuth_step_deg(self) -> float:
        return float(np.median(np.diff(self.azimuth_deg))) if self.azimuth_deg.size > 1 else 0.0

    @property
    def elevation_step_deg(self) -> float:
        return float(np.median(-np.diff(self.elevation_deg))) if self.elevation_deg.size > 1 else 0.0

    @property
    def xyz(self) -> np.ndarray:
        """Levelled points (rows, cols, 3) float64, NaN where no return (cached)."""
        if self._xyz is None:
            if self.points is not None:
                pts = self.points.astype(np.float64)
                pts[~self.valid] = np.nan
            else:
                pts = spherical_to_xyz(self.range_m, self.azimuth_deg, self.elevation_deg)
            if any(self.tilt_deg):
                pts = pts @ levelling_rotation(*self.tilt_deg).T
            pts.flags.writeable = self.range_m.flags.writeable  # a shared image stays read-only
            self._xyz = pts
        return self._xyz

    def levelled(self, v: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Levelled points (n, 3) float64 of the pixels ``(v, u)`` (with a return): the values of
        :attr:`xyz` there, without the whole image's array (a 30 M-point scan's is 0.35 GB)."""
        if self.points is not None:
            pts = self.points[v, u].astype(np.float64)
        else:  # spherical_to_xyz's arithmetic, its cosines taken on the whole axes
            az = np.radians(self.azimuth_deg)
            el = np.radians(self.elevation_deg)
            r, ce = self.range_m[v, u].astype(np.float64), np.cos(el)[v]
            pts = np.column_stack([r * ce * np.cos(az)[u], r * ce * np.sin(az)[u], r * np.sin(el)[v]])
        if any(self.tilt_deg):
            pts = pts @ levelling_rotation(*self.tilt_deg).T
        return pts

    # ---- Arrow / Parquet form -------------------------------------------------------------
    def to_table(self) -> pa.Table:
        """Valid pixels as an Arrow table (row, col, range_m, x, y, z[, intensity, r, g, b]).

        The image geometry (angles, tilt) lives in the schema metadata so that the organised
        image is restored exactly by :meth:`from_table`.
        """
        if self._xyz is None and self.points is not None and not any(self.tilt_deg):
            from forestmap_assets.core.features._image_kernels import gather_points

            # already the levelled float32 values: one pass (0.1 -> 0.02 s a 2.3 M-point scan)
            v, u, r, *xyz = gather_points(self.range_m, self.points)
        else:
            v, u = np.nonzero(self.valid)
            pts = self._xyz[v, u] if self._xyz is not None else self.levelled(v, u)
            r, xyz = self.range_m[v, u], [pts[:, i].astype(np.float32) for i in range(3)]
        cols = {
            "row": pa.array(v.astype(np.int32, copy=False)),
            "col": pa.array(u.astype(np.int32, copy=False)),
            "range_m": pa.array(r),
            **{c: pa.array(xyz[i]) for i, c in enumerate("xyz")},
        }
        if self.intensity is not None:
            cols["intensity"] = pa.array(self.intensity[v, u])
        if self.rgb is not None:
            for i, name in enumerate("rgb"):
                cols[name] = pa.array(self.rgb[v, u, i])
        meta = {
            "forestmap.kind": "range_image",
            "azimuth_deg": json.dumps(self.azimuth_deg.tolist()),
            "elevation_deg": json.dumps(self.elevation_deg.tolist()),
            "tilt_deg": json.dumps(list(map(float, self.tilt_deg))),
            "has_rgb": json.dumps(self.rgb is not None),
            "has_intensity": json.dumps(self.intensity is not None),
            "has_points": json.dumps(self.points is not None),
        }
        return pa.table(cols).replace_schema_metadata({k: str(v) for k, v in meta.items()})

    @classmethod
    def from_table(cls, table: pa.Table) -> RangeImage:
        """The organised image of a :meth:`to_table` table (one scatter per channel through
        the pixels' flat indices). Read-only, and shared: the same table gives the same image
        object (its levelled points computed once for all the stages of a run)."""
        if _DECODED and _DECODED[0][0]() is table:
            return _DECODED[0][1]
        from forestmap_assets.core.features._image_kernels import scatter_points

        meta = {k.decode(): v.decode() for k, v in (table.schema.metadata or {}).items()}
        az = np.asarray(json.loads(meta["azimuth_deg"]), dtype=np.float64)
        el = np.asarray(json.loads(meta["elevation_deg"]), dtype=np.float64)
        tilt = tuple(json.loads(meta.get("tilt_deg", "[0, 0]")))
        shape = (el.size, az.size)
        flat = table.column("row").to_numpy().astype(np.int64) * shape[1]
        flat += table.column("col").to_numpy()

        def channel(name: str, fill, dtype) -> np.ndarray:
            out = np.full(shape[0] * shape[1], fill, dtype=dtype)
            out[flat] = table.column(name).to_numpy()
            return out.reshape(shape)

        rng = channel("range_m", np.nan, np.float32)
        intensity = rgb = None
        if json.loads(meta.get("has_intensity", "false")):
            intensity = channel("intensity", np.nan, np.float32)
        if json.loads(meta.get("has_rgb", "false")):
            rgb = np.stack([channel(name, 0, np.uint8) for name in "rgb"], axis=-1)
        points = None
        if json.loads(meta.get("has_points", "false")):  # back to the scanner frame
            rot = levelling_rotation(*tilt) if any(tilt) else np.eye(3)
            points = np.full((shape[0] * shape[1], 3), np.nan, dtype=np.float32)
            scatter_points(flat, *(table.column(c).to_numpy() for c in "xyz"), rot, points)
            points = points.reshape(shape + (3,))
        image = cls(rng, az, el, (float(tilt[0]), float(tilt[1])), intensity, rgb, points)
        for array in (image.range_m, image.azimuth_deg, image.elevation_deg, intensity, rgb, image.points):
            if array is not None:
                array.flags.writeable = False
        _DECODED[:] = [(weakref.ref(table, _forget_decoded), image)]
        return image
