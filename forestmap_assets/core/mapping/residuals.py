"""Residuals of the optimal map and the thesis's consistency rule (Th. Eq. 6.4, JP eq. (11); spec
8.5).

``e_(i,j) = d_ij - (x_i - x_j)`` for every observation, component-wise in the global frame,
with the observation projected exactly as in the solve; ``r = e / sigma`` with the observation's
projected sigma. A pair is ``inconsistent`` when ``|r|`` of x, y or heading exceeds
``residual_sigmas`` (3, Th. 6.4/7.1) or ``|r_z|`` exceeds ``z_residual_sigmas`` (8, inferred
from Table 7.1: near-vertical trunks constrain z weakly, so the thesis tolerates z at ~6 sigma).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from forestmap_assets.core.mapping.chaining import (
    SD_COLUMNS,
    Covariance,
    observation_arrays,
    project_relative,
    wrap_deg,
)

RESIDUAL_COLUMNS = (
    "scan", "reference", "ex", "ey", "ez", "eheading_deg",
    "rx", "ry", "rz", "rheading", "verdict",
)
_E = ("ex", "ey", "ez", "eheading_deg")
_R = ("rx", "ry", "rz", "rheading")
COMPONENT_NAMES = ("x", "y", "z", "heading")


def residual_arrays(
    i: np.ndarray, j: np.ndarray, d_g: np.ndarray, sd_g: np.ndarray, poses: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Signed residuals ``e`` (M, 4) of Eq. (11) and normalised ``r = e / sigma`` (M, 4).

    ``d_g`` are the projected observations of ``x_i - x_j``, ``sd_g`` their projected sigmas,
    ``poses`` (N, 4) the estimated global poses; the heading residual is wrapped to (-180, 180].
    """
    e = np.asarray(d_g, dtype=float) - (poses[i] - poses[j])
    e[:, 3] = wrap_deg(e[:, 3])
    with np.errstate(divide="ignore", invalid="ignore"):
        r = e / np.asarray(sd_g, dtype=float)
    return e, r


def normalised_excess(
    r: np.ndarray, residual_sigmas: float = 3.0, z_residual_sigmas: float = 8.0
) -> np.ndarray:
    """``|r|`` divided by each component's threshold (M, 4); > 1 means the component fails."""
    limits = np.array([residual_sigmas, residual_sigmas, z_residual_sigmas, residual_sigmas])
    return np.abs(np.asarray(r, dtype=float)) / limits


def residual_verdicts(
    r: np.ndarray, residual_sigmas: float = 3.0, z_residual_sigmas: float = 8.0
) -> np.ndarray:
    """``"ok"`` / ``"inconsistent"`` per observation from its normalised residuals (spec 8.5)."""
    bad = (normalised_excess(r, residual_sigmas, z_residual_sigmas) > 1.0).any(axis=1)
    return np.where(bad, "inconsistent", "ok")


def residual_table(
    scan: np.ndarray,
    reference: np.ndarray,
    e: np.ndarray,
    r: np.ndarray,
    residual_sigmas: float = 3.0,
    z_residual_sigmas: float = 8.0,
) -> pd.DataFrame:
    """Residuals in the ``residuals.csv`` schema (DESIGN.md 4)."""
    out = pd.DataFrame({"scan": np.asarray(scan, dtype=str),
                        "reference": np.asarray(reference, dtype=str)})
    out[list(_E)] = np.asarray(e, dtype=float).reshape(-1, 4)
    out[list(_R)] = np.asarray(r, dtype=float).reshape(-1, 4)
    out["verdict"] = residual_verdicts(out[list(_R)].to_numpy(), residual_sigmas, z_residual_sigmas)
    return out


def residuals_for_poses(
    observations: pd.DataFrame,
    poses: pd.DataFrame,
    *,
    covariance: Covariance = "published",
    residual_sigmas: float = 3.0,
    z_residual_sigmas: float = 8.0,
) -> pd.DataFrame:
    """Eq. (11) residuals of ``observations`` against given global ``poses`` (e.g. chained ones).

    Each observation is projected with the heading of its reference in ``poses`` (Eq. 6.1) and
    its heading unwrapped to the pose difference (``covariance="full"`` takes the reference's
    ``sd_heading_deg`` as the sigma of ``phi_tot``); rows with an unregistered (NaN) end are left
    out. Returns the ``residuals.csv`` schema.
    """
    p = poses[poses["registered"].astype(bool)]
    scans = list(p["scan"].astype(str))
    x = p[["x", "y", "z", "heading_deg"]].to_numpy(dtype=float)
    i, j, d, sd = observation_arrays(observations, scans)
    keep = (i >= 0) & (j >= 0) & (i != j)
    i, j, d, sd = i[keep], j[keep], d[keep].copy(), sd[keep]
    pred = x[i, 3] - x[j, 3]
    d[:, 3] = pred + wrap_deg(d[:, 3] - pred)
    hv = (p["sd_heading_deg"].to_numpy(dtype=float) ** 2 if "sd_heading_deg" in p
          else np.zeros(len(p)))
    dg, cg = project_relative(d, sd, x[j, 3], hv[j], covariance)
    sd_g = np.sqrt(np.diagonal(cg, axis1=1, axis2=2))
    e, r = residual_arrays(i, j, dg, sd_g, x)
    return residual_table(np.array(scans)[i], np.array(scans)[j], e, r,
                          residual_sigmas, z_residual_sigmas)


def variance_factors(residuals: pd.DataFrame, n_placed: int, min_dof: int = 3) -> np.ndarray:
    """Per component (x, y, z, heading) the root of the a posteriori variance factor of the
    optimal map, ``s0 = sqrt(sum r^2 / (M - n_placed + 1))`` over its ``M`` consistent
    observations (normalised residuals ``r``; one less unknown pose than placed scans): about 1
    when the links' sigmas hold, larger when the loops close worse than they say (inferred,
    issue 19: Sylva survey 36, 1.3 / 1.7 in x / y, scans 2 sd off). Ones when the redundancy
    is below ``min_dof`` or ``min_dof`` is 0."""
    ok = residuals[residuals["verdict"] == "ok"] if "verdict" in residuals else residuals
    dof = len(ok) - max(int(n_placed) - 1, 0)
    if not min_dof or dof < min_dof:
        return np.ones(4)
    r = ok[list(_R)].to_numpy(float)
    return np.sqrt(np.nansum(r**2, axis=0) / dof)


def with_variance_factors(poses: pd.DataFrame, factors: np.ndarray) -> pd.DataFrame:
    """``poses`` with ``sd_x, sd_y, sd_z, sd_heading_deg`` times ``factors`` where they exceed
    1: a variance factor below 1 may be chance with a few loops, and sigmas are not shrunk."""
    f = np.maximum(np.nan_to_num(np.asarray(factors, float), nan=1.0), 1.0)
    if np.all(f == 1.0):
        return poses
    out = poses.copy()
    for col, k in zip(SD_COLUMNS, f, strict=True):
        out[col] = out[col].to_numpy(float) * k
    return out
