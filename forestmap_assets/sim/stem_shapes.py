"""Realistic stems of the virtual forest (issue 19): ``make_forest(stems="realistic")``.

The ``circular`` stems of :mod:`.stems` are straight leaning cones with a 1-4 mm ellipse. The
realistic stems keep that table (same DBH, height, position, lean and taper draws, so both
models of one seed share the plot) and add columns for the shape below. ``h`` is the vertical
height above ``z_base``, ``psi`` the angle about the local axis from the x axis projected
perpendicular to it (as in :mod:`.stems`)::

    axis(h)   = (x_base + lean_x h, y_base + lean_y h, z_base + h)
                + sweep_m sin(pi h / height_m) (cos sweep_deg, sin sweep_deg, 0)      sweep
    s(h)      = clip(1 - h / flare_height_m, 0, 1)^2                       flare profile
    R(h)      = r_base_m - taper_m_per_m h + flare_m s(h)                  mean radius
    c(h)      = c13 (1 + 0.3 sin(2 pi (h - 1.3) / flat_wave_m)),  c13 = f / (2 - f)
    theta(h)  = ellipse_deg + twist_deg_per_m (h - 1.3)
    r(h, psi) = R(h) (1 + c(h) cos 2 (psi - theta(h)))                     out of round
                + lobe_m s(h) g(n_lobes (psi - lobe_phase_deg))            flutes, buttresses
                + bark(h, psi)                                             bark relief

``f = flattening`` = 1 - smallest / largest diameter at 1.3 m (5-15 %); the orientation twists
slowly (a few deg/m) and the flattening varies by +-30 % over ``flat_wave_m`` (4-10 m).
``g(x) = 8/5 (((1 + cos x) / 2)^2 - 3/8)`` has zero mean and ridges of height 1: ``n_lobes``
(3-6) buttress ridges that fade out, with the flare, over the lowest ``flare_height_m``
(0.5-1.0 m). ``bark`` is a zero-mean Gaussian random field (sum of ``BARK_MODES`` waves) with
standard deviation ``bark_m / 2`` (``bark_m`` 5-20 mm: the typical crevice depth, +-1 sd),
correlated over ``bark_corr_m`` (2-5 cm) around and 2.5 times that along the stem (vertical
ridges), thinner where the stem is thin.

**Truth.** The flare is zero from 1.0 m up and ``g`` and ``bark`` average out, so the mean
radius at breast height is ``R(1.3) = r_base_m - 1.3 taper_m_per_m`` and ``dbh_m = 2 R(1.3)``
(:func:`~.stems.breast_height_table`): the mean of the section's diameters through its centre
over all directions, which for this section is also the mean of its largest and smallest
diameter (cross-calipering). A girth tape around the smooth section would read
``dbh_girth_m`` = perimeter / pi (written too; larger by ~c^2, < 1 %). ``x, y`` of the tree
are the centre of that section: the axis at 1.3 m, with lean and sweep. ``a2_m, phase2_deg``
hold the ellipse's ``R c, theta`` at 1.3 m (``a3_m = 0``), so the first-order section of
:mod:`.stems` still describes it.

**Forks** (``fork_share`` of the trees tall enough): a second leader starts on the main axis
at ``fork_h_m`` (2-8 m; point ``fork_x, fork_y, fork_z``) with radius ``fork_r_m`` (55-80 % of
the main stem there), leaves it at ``fork_angle_deg`` (15-35 deg) towards ``fork_az_deg`` and
bends back to the main stem's lean over ``fork_bend_m``::

    fork_axis(h) = fork point + (h - fork_h_m) (lean_x, lean_y, 1)
                   + tan(fork_angle) fork_bend_m (1 - exp(-(h - fork_h_m) / fork_bend_m)) (cos, sin, 0)

tapering linearly to 1.5 cm at ``fork_top_m``. The main stem continues unchanged. Columns are
NaN for trees without a fork.

**Dead branches** (:func:`stub_tubes`): stubs 2-5 cm thick, reaching 0.1-0.8 m beyond the
bark at 1-6 m, at -25..45 deg from the horizontal. All numbers are (inferred)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from forestmap_assets.sim.scene_mesh import ring_tube_mesh, tube_mesh
from forestmap_assets.sim.stems import BREAST_HEIGHT_M, sweep_offset

STEM_MODELS = ("circular", "realistic")

SHAPE_COLUMNS = [
    "dbh_girth_m",
    "flattening",
    "ellipse_deg",
    "twist_deg_per_m",
    "flat_wave_m",
    "flare_m",
    "flare_height_m",
    "n_lobes",
    "lobe_m",
    "lobe_phase_deg",
    "bark_m",
    "bark_corr_m",
    "sweep_m",
    "sweep_deg",
    "fork_h_m",
    "fork_x",
    "fork_y",
    "fork_z",
    "fork_az_deg",
    "fork_angle_deg",
    "fork_bend_m",
    "fork_r_m",
    "fork_top_m",
]

BARK_MODES = 48  # plane waves of the bark field
TOP_RADIUS_M = 0.015
STEM_SPACING_M = 0.025  # vertex spacing around the stem (at breast height)
# ring spacing along the stem: (up to height m, spacing m); finest where scans see bark up close
RING_SPACING = ((4.0, 0.03), (8.0, 0.05), (15.0, 0.15), (np.inf, 0.4))


def lobe_profile(x) -> np.ndarray:
    """Buttress ridge profile ``g``: zero mean over a period, ridge top 1, valleys -0.6."""
    return 1.6 * ((0.5 * (1 + np.cos(x))) ** 2 - 0.375)


def flare_profile(h, flare_height_m) -> np.ndarray:
    """``s(h) = clip(1 - h / flare_height, 0, 1)^2`` (1 below the ground, 0 from flare_height)."""
    return np.clip(1.0 - np.asarray(h) / flare_height_m, 0.0, 1.0) ** 2


def realistic_columns(stems: pd.DataFrame, rng: np.random.Generator, *,
                      flattening_range: tuple[float, float] = (0.05, 0.15),
                      twist_deg_per_m: float = 8.0,
                      flare_range: tuple[float, float] = (0.08, 0.35),
                      flare_height_range_m: tuple[float, float] = (0.5, 1.0),
                      lobes: tuple[int, int] = (3, 6),
                      bark_range_m: tuple[float, float] = (0.005, 0.020),
                      bark_corr_range_m: tuple[float, float] = (0.02, 0.05),
                      sweep_range_m: tuple[float, float] = (0.01, 0.08),
                      fork_share: float = 0.2,
                      fork_height_range_m: tuple[float, float] = (2.0, 8.0)) -> pd.DataFrame:
    """The stem table with the realistic shape columns (``SHAPE_COLUMNS``) drawn from ``rng``;
    ``a2_m, phase2_deg`` become the ellipse at 1.3 m and ``a3_m`` 0. Flare and lobe sizes are
    shares of the breast-height radius; all ranges (inferred)."""
    n = len(stems)
    out = stems.copy()
    r_bh = stems["r_base_m"].to_numpy() - stems["taper_m_per_m"].to_numpy() * BREAST_HEIGHT_M
    height = stems["height_m"].to_numpy()
    f = rng.uniform(*flattening_range, n)
    out["flattening"] = f
    out["ellipse_deg"] = rng.uniform(-180.0, 180.0, n)
    out["twist_deg_per_m"] = rng.uniform(-twist_deg_per_m, twist_deg_per_m, n)
    out["flat_wave_m"] = rng.uniform(4.0, 10.0, n)
    out["flare_m"] = r_bh * rng.uniform(*flare_range, n)
    out["flare_height_m"] = rng.uniform(*flare_height_range_m, n)
    out["n_lobes"] = rng.integers(lobes[0], lobes[1] + 1, n)
    out["lobe_m"] = out["flare_m"].to_numpy() * rng.uniform(0.3, 0.8, n)
    out["lobe_phase_deg"] = rng.uniform(-180.0, 180.0, n)
    out["bark_m"] = rng.uniform(*bark_range_m, n)
    out["bark_corr_m"] = rng.uniform(*bark_corr_range_m, n)
    out["sweep_m"] = rng.uniform(*sweep_range_m, n)
    out["sweep_deg"] = rng.uniform(-180.0, 180.0, n)
    c = f / (2.0 - f)
    out["a2_m"] = r_bh * c
    out["phase2_deg"] = out["ellipse_deg"]
    out["a3_m"] = 0.0
    # forks: trees with room for a second leader above the fork
    fh = rng.uniform(*fork_height_range_m, n)
    fork = (rng.random(n) < fork_share) & (fh < 0.6 * height) & (r_bh > 0.06)
    az = rng.uniform(-180.0, 180.0, n)
    ang = rng.uniform(15.0, 35.0, n)
    bend = rng.uniform(2.0, 4.0, n)
    share = rng.uniform(0.55, 0.8, n)
    top = height * rng.uniform(0.8, 0.95, n)
    nan = np.full(n, np.nan)
    out["fork_h_m"] = np.where(fork, fh, nan)
    px, py, pz = stem_axis(out, fh)
    out["fork_x"], out["fork_y"], out["fork_z"] = (np.where(fork, v, nan) for v in (px, py, pz))
    out["fork_az_deg"] = np.where(fork, az, nan)
    out["fork_angle_deg"] = np.where(fork, ang, nan)
    out["fork_bend_m"] = np.where(fork, bend, nan)
    r_fork = stems["r_base_m"].to_numpy() - stems["taper_m_per_m"].to_numpy() * fh
    out["fork_r_m"] = np.where(fork, share * r_fork, nan)
    out["fork_top_m"] = np.where(fork, top, nan)
    out["dbh_girth_m"] = [girth_diameter(row) for _, row in out.iterrows()]
    return out[list(stems.columns) + SHAPE_COLUMNS]


# ---- geometry of one stem ----------------------------------------------------------------
def stem_axis(stems: pd.DataFrame, h) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Axis point (x, y, z) of every row of ``stems`` at vertical heights ``h`` (one per row)."""
    h = np.asarray(h, dtype=np.float64)
    dx, dy = sweep_offset(stems, h)
    return (stems["x_base"].to_numpy() + stems["lean_x"].to_numpy() * h + dx,
            stems["y_base"].to_numpy() + stems["lean_y"].to_numpy() * h + dy,
            stems["z_base"].to_numpy() + h)


def _axis_rings(row, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ring centres and tangents (R, 3) of one stem (a table row) at heights ``h``."""
    a = np.radians(row["sweep_deg"])
    k = np.pi / row["height_m"]
    bow = row["sweep_m"] * np.sin(k * h)
    dbow = row["sweep_m"] * k * np.cos(k * h)
    return _leaning_curve(row, (row["x_base"], row["y_base"], row["z_base"]), h, bow, dbow, a)


def _fork_rings(row, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ring centres and tangents (R, 3) of a tree's second leader at heights ``h``."""
    u = h - row["fork_h_m"]
    a = np.radians(row["fork_az_deg"])
    t = np.tan(np.radians(row["fork_angle_deg"]))
    b = row["fork_bend_m"]
    out = t * b * (1 - np.exp(-u / b))
    dout = t * np.exp(-u / b)
    return _leaning_curve(row, (row["fork_x"], row["fork_y"], row["fork_z"]), u, out, dout, a)


def _leaning_curve(row, origin, u: np.ndarray, off: np.ndarray, doff: np.ndarray,
                   azimuth_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Centres and tangents of a curve rising ``u`` above ``origin`` with the stem's lean and a
    horizontal offset ``off`` (slope ``doff``) toward ``azimuth_rad``."""
    c, s = np.cos(azimuth_rad), np.sin(azimuth_rad)
    centre = np.column_stack([origin[0] + row["lean_x"] * u + off * c,
                              origin[1] + row["lean_y"] * u + off * s,
                              origin[2] + u])
    tangent = np.column_stack([row["lean_x"] + doff * c, row["lean_y"] + doff * s, np.ones_like(u)])
    return centre, tangent


def section_radius(row, h, psi) -> np.ndarray:
    """Smooth radius ``r(h, psi)`` of one stem (no bark relief); ``h`` and ``psi`` broadcast."""
    h, psi = np.asarray(h, dtype=np.float64), np.asarray(psi, dtype=np.float64)
    s = flare_profile(h, row["flare_height_m"])
    mean = row["r_base_m"] - row["taper_m_per_m"] * h + row["flare_m"] * s
    f = row["flattening"]
    c = f / (2 - f) * (1 + 0.3 * np.sin(2 * np.pi * (h - BREAST_HEIGHT_M) / row["flat_wave_m"]))
    theta = np.radians(row["ellipse_deg"] + row["twist_deg_per_m"] * (h - BREAST_HEIGHT_M))
    lobes = row["lobe_m"] * s * lobe_profile(row["n_lobes"] * (psi - np.radians(row["lobe_phase_deg"])))
    return mean * (1 + c * np.cos(2 * (psi - theta))) + lobes


def surface_offset(row, points: np.ndarray, iterations: int = 3) -> tuple[np.ndarray, ...]:
    """Height ``h``, angle ``psi`` and signed distance outside the smooth surface
    (``|p - axis(h)| - r(h, psi)``, bark relief included in the distance) of ``points`` (n, 3)
    relative to one realistic main stem: each point's foot on the curved axis is found by
    moving along the local tangent (a few iterations)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    h = p[:, 2] - row["z_base"]
    for _ in range(iterations):
        centre, tangent = _axis_rings(row, h)
        t = tangent / np.linalg.norm(tangent, axis=1, keepdims=True)
        h = h + ((p - centre) * t).sum(1) * t[:, 2]
    centre, tangent = _axis_rings(row, h)
    t = tangent / np.linalg.norm(tangent, axis=1, keepdims=True)
    v = p - centre
    v -= (v * t).sum(1, keepdims=True) * t
    e1 = np.array([1.0, 0.0, 0.0]) - t[:, :1] * t
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(t, e1)
    psi = np.mod(np.arctan2((v * e2).sum(1), (v * e1).sum(1)), 2 * np.pi)
    return h, psi, np.linalg.norm(v, axis=1) - section_radius(row, h, psi)


def girth_diameter(row, h: float = BREAST_HEIGHT_M, n: int = 2048) -> float:
    """Perimeter / pi of the smooth section at ``h`` (a girth tape, bark relief left out)."""
    psi = np.linspace(0, 2 * np.pi, n, endpoint=False)
    r = section_radius(row, h, psi)
    x, y = r * np.cos(psi), r * np.sin(psi)
    return float(np.hypot(np.diff(x, append=x[0]), np.diff(y, append=y[0])).sum() / np.pi)


def ring_heights(h0: float, h1: float) -> np.ndarray:
    """Ring heights from ``h0`` to ``h1``: ``RING_SPACING`` (fine low on the stem)."""
    out, lo = [], h0
    for top, step in RING_SPACING:
        hi = min(top, h1)
        if hi > lo:
            k = max(1, int(np.ceil((hi - lo) / step)))
            out.append(np.linspace(lo, hi, k + 1)[:-1])
            lo = hi
    out.append([h1])
    return np.concatenate(out)


def bark_field(row, h: np.ndarray, psi: np.ndarray, rng: np.random.Generator,
               r_mean: np.ndarray) -> np.ndarray:
    """Bark relief (R, S) at heights ``h`` (R,) and angles ``psi`` (S,): a sum of ``BARK_MODES``
    waves ``cos(m psi + kappa h + phase)`` (m whole turns, Gaussian spectrum of correlation
    ``bark_corr_m`` around at the breast-height radius and 2.5 x along), sd ``bark_m / 2``
    scaled by the local radius share (thin bark on thin stem parts, 0.25-1)."""
    r_bh = row["r_base_m"] - row["taper_m_per_m"] * BREAST_HEIGHT_M
    corr = row["bark_corr_m"]
    m = np.round(rng.standard_normal(BARK_MODES) * r_bh / corr)
    kappa = rng.standard_normal(BARK_MODES) / (2.5 * corr)
    phase = rng.uniform(0, 2 * np.pi, BARK_MODES)
    a = m[:, None] * psi[None, :]  # (K, S)
    b = kappa[None, :] * h[:, None] + phase[None, :]  # (R, K)
    field = np.cos(b) @ np.cos(a) - np.sin(b) @ np.sin(a)
    sd = 0.5 * row["bark_m"] * np.clip(r_mean / r_bh, 0.25, 1.0)
    return field * (sd * np.sqrt(2.0 / BARK_MODES))[:, None]


def stem_surface(row, rng: np.random.Generator, *, h0: float = -0.3,
                 spacing_m: float = STEM_SPACING_M) -> list[tuple[np.ndarray, np.ndarray]]:
    """Mesh (vertices, faces) of one realistic stem: the main stem from ``h0`` (below the
    ground) to the top and, when it forks, the second leader. Vertices every ``spacing_m``
    around at breast height (32-160 per ring) and every ``RING_SPACING`` along."""
    r_bh = row["r_base_m"] - row["taper_m_per_m"] * BREAST_HEIGHT_M
    n_sides = int(np.clip(4 * np.ceil(2 * np.pi * r_bh / spacing_m / 4), 32, 160))
    psi = np.arange(n_sides) * (2 * np.pi / n_sides)
    h = ring_heights(h0, row["height_m"])
    r = section_radius(row, h[:, None], psi[None, :])
    mean = row["r_base_m"] - row["taper_m_per_m"] * h
    r = r + bark_field(row, h, psi, rng, mean)
    r[-1] = np.maximum(r[-1], 0.2 * TOP_RADIUS_M)
    centre, tangent = _axis_rings(row, h)
    pieces = [ring_tube_mesh(centre, tangent, np.maximum(r, 0.002))]
    if np.isfinite(row["fork_h_m"]):
        hf = ring_heights(row["fork_h_m"], row["fork_top_m"])
        u = (hf - hf[0]) / (hf[-1] - hf[0])
        rf = row["fork_r_m"] + u * (TOP_RADIUS_M - row["fork_r_m"])
        n_f = int(np.clip(4 * np.ceil(2 * np.pi * row["fork_r_m"] / spacing_m / 4), 16, 96))
        psi_f = np.arange(n_f) * (2 * np.pi / n_f)
        c = 0.5 * row["flattening"] / (2 - row["flattening"])
        theta = np.radians(row["ellipse_deg"])
        rr = rf[:, None] * (1 + c * np.cos(2 * (psi_f[None, :] - theta)))
        rr = rr + bark_field(row, hf, psi_f, rng, rf)
        centre, tangent = _fork_rings(row, hf)
        pieces.append(ring_tube_mesh(centre, tangent, np.maximum(rr, 0.002)))
    return pieces


def stub_tubes(stems: pd.DataFrame, rng: np.random.Generator, *,
               per_m_range: tuple[float, float] = (0.2, 1.5),
               height_range_m: tuple[float, float] = (1.0, 6.0),
               diameter_range_m: tuple[float, float] = (0.02, 0.05),
               length_range_m: tuple[float, float] = (0.1, 0.8),
               elevation_range_deg: tuple[float, float] = (-25.0, 45.0)):
    """Dead branches and stubs on the lower trunks: ``Poisson(rate x span)`` per tree (rate
    ``per_m_range`` per metre of the 1-6 m span, below 60 % of the tree height), thin tubes
    from the stem axis out through the bark. Returns vertices, faces and the row index of the
    tree of each stub, face -> stub index (8 sides, 2 rings: 16 faces per stub)."""
    n = len(stems)
    height = stems["height_m"].to_numpy()
    lo = height_range_m[0]
    hi = np.minimum(height_range_m[1], 0.6 * height)
    count = rng.poisson(rng.uniform(*per_m_range, n) * np.maximum(hi - lo, 0.0))
    tree = np.repeat(np.arange(n), count)
    if not tree.size:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), tree, np.zeros(0, np.int64)
    sub = stems.iloc[tree]
    h = lo + rng.random(tree.size) * (hi[tree] - lo)
    az = rng.uniform(-np.pi, np.pi, tree.size)
    el = np.radians(rng.uniform(*elevation_range_deg, tree.size))
    d = np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    start = np.column_stack(stem_axis(sub, h))
    r_stem = sub["r_base_m"].to_numpy() - sub["taper_m_per_m"].to_numpy() * h
    out = r_stem * 1.1 + rng.uniform(*length_range_m, tree.size)
    rs = 0.5 * rng.uniform(*diameter_range_m, tree.size)
    v, f = tube_mesh(start, start + out[:, None] * d, rs, 0.6 * rs, n_sides=8, n_rings=2)
    return v, f, tree, np.repeat(np.arange(tree.size), 16)
