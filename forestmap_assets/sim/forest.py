"""A virtual forest plot as one labelled triangle mesh (synthetic data for spec 10.1 / 10.6 / 13).

The plot imitates the thesis's forest site (spec 10.1: natural forest, about 40 m square, six
tripod positions T, S, R, Q, O, N, trunks only): uneven ground (:mod:`.ground`), leaning and
tapering stems with slightly non-circular cross-sections (:mod:`.stems`), crowns of branches and
foliage blobs above a few metres, and understorey clutter near the ground, joined into one
:class:`~.scene_mesh.SceneMesh`. All numeric choices of the virtual forest are (inferred): the
thesis describes its site only in words; they are keyword arguments of :func:`make_forest`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from forestmap_assets.sim.ground import Ground, ground_mesh, make_ground
from forestmap_assets.sim.scene_mesh import (
    KIND_BRANCH,
    KIND_FOLIAGE,
    KIND_GROUND,
    KIND_STEM,
    KIND_UNDERSTOREY,
    SceneMesh,
    blob_mesh,
    box_mesh,
    concat_meshes,
    tube_mesh,
)
from forestmap_assets.sim.stem_shapes import (
    STEM_MODELS,
    realistic_columns,
    stem_axis,
    stem_surface,
    stub_tubes,
)
from forestmap_assets.sim.stems import (
    BREAST_HEIGHT_M,
    STEM_COLUMNS,
    breast_height_table,
    place_stems,
    sample_dbh,
    stem_height,
)


# ---- placement -------------------------------------------------------------------------------
def scan_layout(
    n: int,
    plot_size: float,
    rng: np.random.Generator,
    *,
    spacing_m: float = 7.0,
    jitter_m: float = 0.75,
    edge_margin_m: float = 5.0,
) -> np.ndarray:
    """Scan positions (n, 2): a perturbed serpentine (zigzag) grid centred in the plot so that
    neighbours are about ``spacing_m`` apart (5-10 m, inferred from Fig. 6.10, spec 10.1)."""
    ncols = int(np.ceil(np.sqrt(n)))
    nrows = int(np.ceil(n / ncols))
    span = max(ncols, nrows) - 1
    step = spacing_m if span == 0 else min(spacing_m, (plot_size - 2 * edge_margin_m) / span)
    k = np.arange(n)
    row, col = k // ncols, k % ncols
    col = np.where(row % 2 == 1, ncols - 1 - col, col)  # serpentine order
    xy = np.stack([(col - (ncols - 1) / 2) * step, (row - (nrows - 1) / 2) * step], axis=1)
    return xy + rng.uniform(-jitter_m, jitter_m, (n, 2))


# ---- the forest ------------------------------------------------------------------------------
@dataclass
class Forest:
    """A virtual plot: ground, stems (table, world frame), scan positions and the mesh."""

    plot_size: float
    ground: Ground
    stems: pd.DataFrame
    scan_xy: np.ndarray
    mesh: SceneMesh

    def trees_at_breast_height(self) -> pd.DataFrame:
        """Truth per tree (world frame): ``tree_id, x, y, z, dbh_m`` (axis at 1.3 m; z ground)."""
        return breast_height_table(self.stems)


def make_forest(
    trees: int = 40,
    plot_size: float = 40.0,
    *,
    scan_xy: np.ndarray | None = None,
    n_scans: int = 6,
    seed: int | np.random.Generator = 0,
    scan_clearance_m: float = 2.5,
    min_tree_gap_m: float = 0.8,
    max_lean_deg: float = 8.0,
    lean_sigma_deg: float = 2.5,
    crown_base_range_m: tuple[float, float] = (3.0, 6.0),
    branches_per_m: float = 1.2,
    foliage_porosity: float = 0.3,
    understorey_per_m2: float = 0.04,
    understorey_clearance_m: float = 2.0,
    stem_sides: int = 48,
    stem_rings: int = 24,
    ground_margin_m: float = 20.0,
    ground_cell_m: float = 0.5,
    ground_kwargs: dict | None = None,
    stems: str = "circular",
    shape_kwargs: dict | None = None,
    dense_understorey_per_m2: float = 0.2,
    dense_clearance_m: float = 1.2,
) -> Forest:
    """Build a virtual forest plot (square ``plot_size`` m centred at the origin).

    ``trees`` stems with DBH from :func:`sample_dbh`, leaning ``|N(0, lean_sigma_deg)|`` (at
    most ``max_lean_deg``), linear taper to ~1.5 cm at the top, elliptical/triangular
    cross-section perturbation of 1-4 mm and 0-2 mm, crowns of branches (tubes) and porous
    foliage blobs from 3-6 m up, understorey bushes/saplings/boxes below ~1 m. Stems keep
    ``scan_clearance_m`` from the scan positions (``scan_xy`` or :func:`scan_layout` of
    ``n_scans``), understorey ``understorey_clearance_m``. All values (inferred).

    ``stems="realistic"`` (issue 19, :mod:`.stem_shapes`) draws the same plot (positions, DBH,
    heights, leans, crowns, the understorey above) and then, from a stream spawned off
    ``seed``, gives the stems sweep, out-of-round sections, buttress flare and flutes, bark
    relief and forks (``shape_kwargs`` to :func:`~.stem_shapes.realistic_columns`), adds dead
    branch stubs on the lower trunks and a dense understorey layer
    (``dense_understorey_per_m2`` saplings, bushes and dead wood, ``dense_clearance_m`` from
    the scans; :func:`dense_understorey`).
    """
    if stems not in STEM_MODELS:
        raise ValueError(f"stems: {stems!r} is not one of {list(STEM_MODELS)}")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    # realistic shapes come from their own stream, so the plot's draws stay those of circular
    extra = rng.spawn(1)[0] if stems == "realistic" else None
    ground = make_ground(rng, **(ground_kwargs or {}))
    if scan_xy is None:
        scan_xy = scan_layout(n_scans, plot_size, rng)
    scan_xy = np.asarray(scan_xy, dtype=np.float64).reshape(-1, 2)

    # stems
    dbh = sample_dbh(trees, rng)
    height = stem_height(dbh, rng)
    r_bh = dbh / 2
    taper = (r_bh - 0.015) / (height - BREAST_HEIGHT_M)
    r_base = r_bh + taper * BREAST_HEIGHT_M
    xy = place_stems(
        r_base, scan_xy, plot_size, rng, scan_clearance_m=scan_clearance_m, min_gap_m=min_tree_gap_m
    )
    lean = np.radians(np.minimum(np.abs(rng.normal(0, lean_sigma_deg, trees)), max_lean_deg))
    lean_dir = rng.uniform(-np.pi, np.pi, trees)
    harm = np.stack(
        [
            rng.uniform(0.001, 0.004, trees),
            rng.uniform(-np.pi, np.pi, trees),
            rng.uniform(0.0, 0.002, trees),
            rng.uniform(-np.pi, np.pi, trees),
        ],
        axis=1,
    )
    crown_base = np.minimum(rng.uniform(*crown_base_range_m, trees), 0.6 * height)
    table = pd.DataFrame(
        {
            "tree_id": np.arange(1, trees + 1),
            "x_base": xy[:, 0],
            "y_base": xy[:, 1],
            "z_base": ground.height(xy[:, 0], xy[:, 1]),
            "lean_x": np.tan(lean) * np.cos(lean_dir),
            "lean_y": np.tan(lean) * np.sin(lean_dir),
            "r_base_m": r_base,
            "taper_m_per_m": taper,
            "height_m": height,
            "crown_base_m": crown_base,
            "a2_m": harm[:, 0],
            "phase2_deg": np.degrees(harm[:, 1]),
            "a3_m": harm[:, 2],
            "phase3_deg": np.degrees(harm[:, 3]),
        }
    )[STEM_COLUMNS]
    base = table[["x_base", "y_base", "z_base"]].to_numpy()
    slope = np.column_stack([table["lean_x"], table["lean_y"], np.ones(trees)])
    idx = np.arange(trees)
    part = 1  # 0 is the ground
    pieces = []
    gv, gf = ground_mesh(ground, plot_size / 2 + ground_margin_m, ground_cell_m)
    pieces.append((gv, gf, np.full(len(gf), KIND_GROUND), np.full(len(gf), -1), np.zeros(len(gf))))
    if extra is None:

        def axis_at(i, h):  # stem axis points of trees (row index) at heights h
            return base[i] + np.asarray(h)[:, None] * slope[i]

        h0 = np.full(trees, -0.3)  # the tube starts below the ground
        sv, sf = tube_mesh(
            axis_at(idx, h0),
            axis_at(idx, height),
            r_base - taper * h0,
            r_base - taper * height,
            n_sides=stem_sides,
            n_rings=stem_rings,
            harmonics=harm,
        )
        per_stem = 2 * (stem_rings - 1) * stem_sides
        stem_owner = np.repeat(idx, per_stem)
        pieces.append((sv, sf, np.full(len(sf), KIND_STEM), stem_owner + 1, part + stem_owner))
        part += trees
    else:
        table = realistic_columns(table, extra, **(shape_kwargs or {}))

        def axis_at(i, h):  # stem axis points (with sweep) of trees (row index) at heights h
            return np.column_stack(stem_axis(table.iloc[i], h))

        part = _realistic_stems(table, extra, pieces, part)
    stems = table

    # crowns: branches from the stem axis, foliage blobs at their ends and at the top
    crown_len = np.maximum(height * 0.95 - crown_base, 0.5)
    n_br = np.maximum(3, np.round(branches_per_m * crown_len)).astype(int)
    bt = np.repeat(idx, n_br)
    u = rng.random(bt.size)
    hb = crown_base[bt] + u * crown_len[bt]
    crown_r = 0.8 + 6.0 * dbh[bt]  # crown radius (inferred)
    length = crown_r * rng.uniform(0.5, 1.0, bt.size) * (1 - 0.6 * u)
    az = rng.uniform(-np.pi, np.pi, bt.size)
    up = np.radians(rng.uniform(10, 50, bt.size))
    direction = np.stack([np.cos(up) * np.cos(az), np.cos(up) * np.sin(az), np.sin(up)], axis=1)
    start = axis_at(bt, hb)
    end = start + length[:, None] * direction
    rb = np.minimum(0.4 * (r_base[bt] - taper[bt] * hb), rng.uniform(0.01, 0.04, bt.size))
    bv, bf = tube_mesh(start, end, rb, 0.3 * rb, n_sides=6, n_rings=2)
    br_owner = np.repeat(np.arange(bt.size), 2 * 6)
    pieces.append((bv, bf, np.full(len(bf), KIND_BRANCH), bt[br_owner] + 1, part + br_owner))
    part += bt.size

    top = axis_at(idx, height)
    blob_c = np.concatenate([end, top])
    blob_tree = np.concatenate([bt, idx])
    blob_size = np.concatenate(
        [0.25 + 0.35 * crown_r / 2 * rng.uniform(0.5, 1.0, bt.size), 0.4 + 2.0 * dbh]
    )
    radii = blob_size[:, None] * np.array([[1.0, 1.0, 0.7]])
    fv, ff, f_owner = blob_mesh(blob_c, radii, rng, porosity=foliage_porosity)
    pieces.append((fv, ff, np.full(len(ff), KIND_FOLIAGE), blob_tree[f_owner] + 1, part + f_owner))
    part += blob_c.shape[0]

    # understorey: bushes, saplings and boxes (stumps, stones) away from scans and stems
    n_u = int(round(understorey_per_m2 * plot_size**2))
    if n_u:
        size = rng.uniform(0.2, 0.6, 8 * n_u + 64)
        cand = rng.uniform(-plot_size / 2, plot_size / 2, (size.size, 2))
        ok = (
            np.linalg.norm(cand[:, None] - scan_xy[None], axis=2)
            >= understorey_clearance_m + size[:, None]
        ).all(1)
        ok &= (
            np.linalg.norm(cand[:, None] - xy[None], axis=2) >= r_base[None] + size[:, None] + 0.1
        ).all(1)
        cand, size = cand[ok][:n_u], size[ok][:n_u]
        n_u = len(size)
        kind_u = rng.choice(3, n_u, p=[0.45, 0.35, 0.20])
        zc = ground.height(cand[:, 0], cand[:, 1])
        for k, gen in ((0, "bush"), (1, "sapling"), (2, "box")):
            m = np.flatnonzero(kind_u == k)
            if not m.size:
                continue
            if gen == "bush":
                rad = size[m, None] * np.array([[1.0, 1.0, 0.8]])
                c = np.column_stack([cand[m], zc[m] + 0.5 * rad[:, 2]])
                v, f, own = blob_mesh(c, rad, rng, jitter=0.25, porosity=0.2)
                own = m[own]
            elif gen == "sapling":
                hgt = rng.uniform(0.5, 1.3, m.size)
                lean_v = rng.normal(0, 0.08, (m.size, 2))
                p0 = np.column_stack([cand[m], zc[m] - 0.1])
                p1 = np.column_stack([cand[m] + lean_v * hgt[:, None], zc[m] + hgt])
                rs = rng.uniform(0.005, 0.02, m.size)
                v, f = tube_mesh(p0, p1, rs, 0.4 * rs, n_sides=6, n_rings=2)
                own = m[np.repeat(np.arange(m.size), 12)]
                cv, cf, cown = blob_mesh(
                    p1,
                    rng.uniform(0.1, 0.3, (m.size, 1)) * [[1, 1, 0.8]],
                    rng,
                    jitter=0.25,
                    porosity=0.3,
                )
                f = np.concatenate([f, cf + len(v)])
                v = np.concatenate([v, cv])
                own = np.concatenate([own, m[cown]])
            else:
                dims = np.column_stack(
                    [
                        size[m],
                        size[m] * rng.uniform(0.5, 1.0, m.size),
                        rng.uniform(0.1, 0.4, m.size) + 0.1,
                    ]
                )
                v, f = box_mesh(
                    np.column_stack([cand[m], zc[m] - 0.1]), dims, rng.uniform(0, np.pi, m.size)
                )
                own = m[np.repeat(np.arange(m.size), 12)]
            pieces.append(
                (v, f, np.full(len(f), KIND_UNDERSTOREY), np.full(len(f), -1), part + own)
            )
        part += n_u
    if extra is not None and dense_understorey_per_m2 > 0:
        flare = r_base + stems["flare_m"].to_numpy()
        part = dense_understorey(ground, plot_size, scan_xy, xy, flare, extra, pieces, part,
                                 per_m2=dense_understorey_per_m2, clearance_m=dense_clearance_m)
    return Forest(plot_size, ground, stems, scan_xy, concat_meshes(pieces))


def _realistic_stems(stems: pd.DataFrame, rng: np.random.Generator, pieces: list,
                     part: int) -> int:
    """Append the realistic stem meshes (main stems: parts ``part + row``; second leaders and
    stubs after them) to ``pieces``; returns the next free part id."""
    n = len(stems)
    ids = stems["tree_id"].to_numpy()
    leaders = []
    for i, (_, row) in enumerate(stems.iterrows()):
        main, *fork = stem_surface(row, rng)
        pieces.append((*main, np.full(len(main[1]), KIND_STEM), np.full(len(main[1]), ids[i]),
                       np.full(len(main[1]), part + i)))
        leaders += [(v, f, ids[i]) for v, f in fork]
    part += n
    for k, (v, f, tid) in enumerate(leaders):
        pieces.append((v, f, np.full(len(f), KIND_STEM), np.full(len(f), tid),
                       np.full(len(f), part + k)))
    part += len(leaders)
    v, f, tree, own = stub_tubes(stems, rng)
    if len(f):
        pieces.append((v, f, np.full(len(f), KIND_BRANCH), ids[tree[own]], part + own))
        part += tree.size
    return part


def dense_understorey(ground: Ground, plot_size: float, scan_xy: np.ndarray,
                      stem_xy: np.ndarray, stem_r: np.ndarray, rng: np.random.Generator,
                      pieces: list, part: int, *, per_m2: float = 0.2,
                      clearance_m: float = 1.2) -> int:
    """A dense understorey layer (realistic forest, inferred): ``per_m2`` objects, half
    saplings (stems 1-4 cm thick, 0.5-3 m tall, leaning, with one or two small porous leaf
    blobs), 40 % bushes (clusters of 1-3 blobs, 0.15-0.6 m), 10 % dead wood (lying logs
    5-20 cm thick, 0.5-3 m long), ``clearance_m`` from the scans and clear of the stems
    (``stem_r``: radius at the ground). Appended to ``pieces``; returns the next part id."""
    n = int(round(per_m2 * plot_size**2))
    if not n:
        return part
    size = rng.uniform(0.05, 0.4, 4 * n + 64)
    cand = rng.uniform(-plot_size / 2, plot_size / 2, (size.size, 2))
    ok = (np.linalg.norm(cand[:, None] - scan_xy[None], axis=2) >= clearance_m + size[:, None]).all(1)
    ok &= (np.linalg.norm(cand[:, None] - stem_xy[None], axis=2)
           >= stem_r[None] + size[:, None] + 0.05).all(1)
    cand, size = cand[ok][:n], size[ok][:n]
    n = len(size)
    kind = rng.choice(3, n, p=[0.5, 0.4, 0.1])
    zc = ground.height(cand[:, 0], cand[:, 1])

    def add(v, f, own):
        pieces.append((v, f, np.full(len(f), KIND_UNDERSTOREY), np.full(len(f), -1), part + own))

    m = np.flatnonzero(kind == 0)  # saplings
    if m.size:
        hgt = rng.uniform(0.5, 3.0, m.size)
        top = np.column_stack([cand[m] + rng.normal(0, 0.06, (m.size, 2)) * hgt[:, None],
                               zc[m] + hgt])
        rs = 0.5 * rng.uniform(0.01, 0.04, m.size)
        v, f = tube_mesh(np.column_stack([cand[m], zc[m] - 0.1]), top, rs, 0.3 * rs,
                         n_sides=8, n_rings=2)
        add(v, f, m[np.repeat(np.arange(m.size), 16)])
        k = np.repeat(np.arange(m.size), rng.integers(1, 3, m.size))
        c = top[k] - np.column_stack([np.zeros((k.size, 2)), rng.uniform(0, 0.5, k.size) * hgt[k]])
        c[:, :2] += rng.normal(0, 0.1, (k.size, 2))
        rad = rng.uniform(0.1, 0.35, (k.size, 1)) * [[1.0, 1.0, 0.7]]
        v, f, own = blob_mesh(c, rad, rng, jitter=0.3, porosity=0.4)
        add(v, f, m[k[own]])
    m = np.flatnonzero(kind == 1)  # bushes
    if m.size:
        k = np.repeat(np.arange(m.size), rng.integers(1, 4, m.size))
        rad = rng.uniform(0.15, 0.6, (k.size, 1)) * rng.uniform(0.7, 1.0, (k.size, 3))
        c = np.column_stack([cand[m][k] + rng.normal(0, 0.25, (k.size, 2)),
                             zc[m][k] + rng.uniform(0.3, 0.9, k.size) * rad[:, 2]])
        v, f, own = blob_mesh(c, rad, rng, jitter=0.3, porosity=0.25)
        add(v, f, m[k[own]])
    m = np.flatnonzero(kind == 2)  # dead wood on the ground
    if m.size:
        az = rng.uniform(-np.pi, np.pi, m.size)
        half = 0.5 * rng.uniform(0.5, 3.0, m.size)[:, None] * np.column_stack([np.cos(az),
                                                                                np.sin(az)])
        r = 0.5 * rng.uniform(0.05, 0.2, m.size)
        p0, p1 = cand[m] - half, cand[m] + half
        z0 = ground.height(p0[:, 0], p0[:, 1]) + 0.5 * r
        z1 = ground.height(p1[:, 0], p1[:, 1]) + 0.5 * r
        v, f = tube_mesh(np.column_stack([p0, z0]), np.column_stack([p1, z1]), r, 0.8 * r,
                         n_sides=8, n_rings=2)
        add(v, f, m[np.repeat(np.arange(m.size), 16)])
    return part + n
