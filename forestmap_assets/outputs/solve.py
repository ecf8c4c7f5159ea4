"""Core of ``forestmap solve OBSERVATIONS.csv [--order A,B,...] [--out DIR]`` (DESIGN.md 3-4).

Reads a table of pairwise observations (each row the location of ``scan`` in the levelled
frame of ``reference``), solves the optimal map incrementally in the given order (spec 8.4;
or chains it, spec 8.3, with ``MappingParams.method="chain"``), and writes ``poses.csv`` and
``residuals.csv`` atomically.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from forestmap_assets.core.mapping.chaining import (
    OBSERVATION_COLUMNS,
    SD_COLUMNS,
    VALUE_COLUMNS,
    chain_poses,
    wrap_deg,
)
from forestmap_assets.core.mapping.optimal_map import Linearisation, OptimalMap, solve_incremental
from forestmap_assets.core.mapping.residuals import RESIDUAL_COLUMNS, residuals_for_poses
from forestmap_assets.params import MappingParams

POSES_CSV_COLUMNS = (
    "scan", "x", "y", "z", "heading_deg",
    "sd_x", "sd_y", "sd_z", "sd_heading_deg", "registered",
)


class SolveInputError(ValueError):
    """An OBSERVATIONS.csv or ``--order`` that cannot be solved (one-line message)."""


@dataclass
class SolveResult:
    """Poses (``poses.csv`` schema, headings wrapped to (-180, 180]) and residuals
    (``residuals.csv`` schema) of the final map; ``optimal_map`` holds every phase (None for
    ``method="chain"``)."""

    order: list[str]
    reference: str
    poses: pd.DataFrame
    residuals: pd.DataFrame
    optimal_map: OptimalMap | None


def first_appearance_order(observations: pd.DataFrame) -> list[str]:
    """Scans in order of first appearance, reading each row's ``reference`` before its ``scan``
    (so a file of new -> older pairs such as Table 6.6 gives T, S, R, Q, O, N)."""
    pairs = observations[["reference", "scan"]].astype(str).to_numpy().reshape(-1)
    return list(dict.fromkeys(pairs))


def _resolve_order(observations: pd.DataFrame, order: Sequence[str] | None) -> list[str]:
    known = first_appearance_order(observations)
    if order is None:
        return known
    order = [str(s).strip() for s in order]
    dup = sorted({s for s in order if order.count(s) > 1})
    if dup:
        raise SolveInputError(f"--order names scan(s) more than once: {', '.join(dup)}")
    unknown = [s for s in order if s not in set(known)]
    if unknown:
        raise SolveInputError(f"--order names scan(s) not in the observations: "
                              f"{', '.join(unknown)} (known: {', '.join(known)})")
    return order + [s for s in known if s not in set(order)]


def solve_observations(
    observations: pd.DataFrame,
    order: list[str] | None,
    params: MappingParams,
    *,
    iterate: bool = False,
    linearisation: Linearisation = "projection",
) -> SolveResult:
    """Optimal map of ``observations`` solved incrementally in ``order`` (spec 8.4).

    ``order`` defaults to the order of first appearance; its first scan is the reference (global
    frame, pose 0 with sigma 0); scans it leaves out are appended in order of appearance.
    ``params.method="optimal"`` re-solves Eq. 3.20-3.21 phase by phase with
    ``params.covariance`` (``published`` / ``full``); ``"chain"`` chains the poses (spec 8.3).
    ``iterate`` (not yet in MappingParams, inferred) re-projects to convergence in every phase;
    ``linearisation="gauss_newton"`` (not yet in MappingParams, beyond the thesis) solves every
    phase to the maximum-likelihood map.
    Residuals of Eq. (11) with verdicts use ``params.residual_sigmas`` / ``z_residual_sigmas``.
    """
    obs = observations.loc[:, list(OBSERVATION_COLUMNS)].copy()
    obs["scan"], obs["reference"] = obs["scan"].astype(str), obs["reference"].astype(str)
    full_order = _resolve_order(obs, order)
    thresholds = dict(residual_sigmas=params.residual_sigmas,
                      z_residual_sigmas=params.z_residual_sigmas)
    if params.method == "chain":
        poses = chain_poses(obs, full_order)
        residuals = residuals_for_poses(obs, poses, covariance=params.covariance, **thresholds)
        om = None
    else:
        om = solve_incremental(obs, full_order, covariance=params.covariance, iterate=iterate,
                               linearisation=linearisation, **thresholds)
        poses, residuals = om.final.poses.copy(), om.final.residuals.copy()
    poses["heading_deg"] = wrap_deg(poses["heading_deg"].to_numpy(dtype=float))
    poses = poses.loc[:, list(POSES_CSV_COLUMNS)].reset_index(drop=True)
    poses["registered"] = poses["registered"].astype(bool)
    residuals = residuals.loc[:, list(RESIDUAL_COLUMNS)].reset_index(drop=True)
    return SolveResult(full_order, full_order[0], poses, residuals, om)


def read_observations(csv_path: str | os.PathLike) -> pd.DataFrame:
    """Read and validate OBSERVATIONS.csv; raise :class:`SolveInputError` with a one-line reason
    naming the file and the column or line (line 1 is the header)."""
    path = Path(csv_path)
    try:
        raw = pd.read_csv(path, dtype=str, keep_default_na=False, skipinitialspace=True)
    except FileNotFoundError:
        raise SolveInputError(f"{path}: file not found") from None
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError, OSError) as exc:
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise SolveInputError(f"{path}: cannot read as CSV ({reason})") from None
    raw.columns = [str(c).strip() for c in raw.columns]
    missing = [c for c in OBSERVATION_COLUMNS if c not in raw.columns]
    if missing:
        raise SolveInputError(f"{path}: missing column(s) {', '.join(missing)} (expected "
                              f"{','.join(OBSERVATION_COLUMNS)})")
    if len(raw) == 0:
        raise SolveInputError(f"{path}: no observations (only a header)")
    obs = pd.DataFrame({c: raw[c].str.strip() for c in ("scan", "reference")})
    for col in ("scan", "reference"):
        empty = np.flatnonzero(obs[col].to_numpy() == "")
        if empty.size:
            raise SolveInputError(f"{path}: line {empty[0] + 2}, column {col}: empty scan id")
    for col in VALUE_COLUMNS + SD_COLUMNS:
        values = pd.to_numeric(raw[col].str.strip(), errors="coerce").to_numpy(dtype=float)
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            raise SolveInputError(f"{path}: line {bad[0] + 2}, column {col}: "
                                  f"{raw[col].iloc[bad[0]]!r} is not a finite number")
        if col in SD_COLUMNS and (values <= 0).any():
            k = int(np.flatnonzero(values <= 0)[0])
            raise SolveInputError(f"{path}: line {k + 2}, column {col}: sigma must be positive, "
                                  f"got {raw[col].iloc[k]}")
        obs[col] = values
    same = np.flatnonzero(obs["scan"].to_numpy() == obs["reference"].to_numpy())
    if same.size:
        raise SolveInputError(f"{path}: line {same[0] + 2}: scan and reference are the same "
                              f"({obs['scan'].iloc[same[0]]})")
    return obs


def _write_atomic(frame: pd.DataFrame, target: Path) -> None:
    """Write ``frame`` to ``target`` via a temporary file in the same folder and os.replace."""
    frame = frame.copy()
    floats = frame.select_dtypes("float").columns
    frame[floats] = frame[floats].round(6) + 0.0  # no "-0.000000"
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, "w", newline="") as fh:
            frame.to_csv(fh, index=False, float_format="%.6f", lineterminator="\n")
        os.replace(tmp, target)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def run_solve(
    csv_path: str | os.PathLike,
    order: Sequence[str] | str | None = None,
    out_dir: str | os.PathLike | None = None,
    params: MappingParams | None = None,
) -> tuple[Path, Path]:
    """``forestmap solve``: validate ``csv_path``, solve in ``order`` (a list or "T,S,R"), write
    ``poses.csv`` and ``residuals.csv`` to ``out_dir`` (default: the CSV's folder).

    Unregistered scans get ``registered=false`` and empty pose columns; ``registered`` is
    written as ``true``/``false``. Raises :class:`SolveInputError` (one line) on bad input.
    """
    path = Path(csv_path)
    obs = read_observations(path)
    if isinstance(order, str):
        order = [s for s in order.split(",")]
    if order is not None and any(not str(s).strip() for s in order):
        raise SolveInputError(f"{path}: --order has an empty scan name")
    try:
        result = solve_observations(obs, None if order is None else list(order),
                                    params or MappingParams())
    except SolveInputError as exc:
        raise SolveInputError(f"{path}: {exc}") from None
    out = Path(out_dir) if out_dir is not None else path.parent
    out.mkdir(parents=True, exist_ok=True)
    poses = result.poses.astype({"registered": object})
    poses["registered"] = np.where(result.poses["registered"], "true", "false")
    poses_path, residuals_path = out / "poses.csv", out / "residuals.csv"
    _write_atomic(poses, poses_path)
    _write_atomic(result.residuals, residuals_path)
    return poses_path, residuals_path
