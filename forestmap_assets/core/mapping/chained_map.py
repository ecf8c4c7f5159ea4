"""The thesis's global map for the parking lot and the corridor: incremental chaining (spec 8.3).

``params.mapping.method = "chain"`` replaces the optimal map (spec 8.4) by chaining: every scan's
global pose is the pose of an already placed scan plus the projected relative observation
(Eq. 6.1), variances summed along the chain (Th. 6.2, Tables 6.4-6.5;
:func:`~.chaining.chain_poses`). Links not on the chain (e.g. a loop closure) are not used;
their residuals against the chained poses (Eq. 6.4) show how far the chain has drifted, and are
reported with their verdicts, never silently dropped.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from forestmap_assets.core.mapping.chaining import Covariance, chain_poses
from forestmap_assets.core.mapping.residuals import residuals_for_poses

RESIDUAL_COLUMNS = ["scan", "reference", "ex", "ey", "ez", "eheading_deg", "rx", "ry", "rz",
                    "rheading", "verdict"]


@dataclass
class ChainedMap:
    """``poses`` (``scan, x, y, z, heading_deg, sd_*, registered``; headings wrapped),
    ``links`` (the observations with ``status`` admitted / unused / unreached, ``role``
    ``chain``, ``step`` and ``reason``) and ``residuals`` (every link between placed scans)."""

    poses: pd.DataFrame
    links: pd.DataFrame
    residuals: pd.DataFrame


def chained_map(
    observations: pd.DataFrame,
    order: Sequence[str],
    *,
    link_choice: str = "latest",
    covariance: Covariance = "published",
    residual_sigmas: float = 3.0,
    z_residual_sigmas: float = 8.0,
    chain_tolerance: float = 1e-6,
) -> ChainedMap:
    """Chain the accepted ``observations`` (``OBSERVATION_COLUMNS``) in ``order`` (``order[0]``
    = reference, spec 8.3). A link is on the chain when its residual against the chained poses
    is zero (below ``chain_tolerance`` in every component: the chain reproduces its own links
    exactly); other links between placed scans are ``unused`` with their residual verdict."""
    from forestmap_assets.core.geometry import wrap_deg

    order = [str(s) for s in order]
    obs = observations.reset_index(drop=True)
    poses = chain_poses(obs, order, link_choice=link_choice)
    poses["heading_deg"] = np.where(poses["registered"],
                                    wrap_deg(poses["heading_deg"].fillna(0.0).to_numpy(float)),
                                    np.nan)
    placed = set(poses.loc[poses["registered"], "scan"])
    res = residuals_for_poses(obs, poses, covariance=covariance,
                              residual_sigmas=residual_sigmas,
                              z_residual_sigmas=z_residual_sigmas)
    links = obs.copy()
    both = links["scan"].astype(str).isin(placed) & links["reference"].astype(str).isin(placed)
    links["status"] = np.where(both, "unused", "unreached").astype(object)
    links["role"] = ""
    links["step"] = -1
    links["reason"] = np.where(both, "", "a sub-map of this link is not placed by the chain")
    if len(res):
        # residuals_for_poses keeps the rows of links between placed scans, in order
        idx = links.index[both.to_numpy()]
        e = res[["ex", "ey", "ez", "eheading_deg"]].to_numpy(float)
        on_chain = (np.abs(e) < chain_tolerance).all(axis=1)
        links.loc[idx[on_chain], "status"] = "admitted"
        links.loc[idx[on_chain], "role"] = "chain"
        rank = {s: k for k, s in enumerate(order)}
        later = np.array([max(rank.get(str(a), -1), rank.get(str(b), -1))
                          for a, b in zip(links.loc[idx, "scan"], links.loc[idx, "reference"],
                                          strict=True)])
        links.loc[idx[on_chain], "step"] = later[on_chain] - 1
        links.loc[idx[on_chain], "reason"] = "chained (Th. 6.2): placed the later sub-map"
        off = idx[~on_chain]
        verdict = res["verdict"].to_numpy()[~on_chain]
        worst = np.abs(res[["rx", "ry", "rz", "rheading"]].to_numpy(float)[~on_chain]).max(
            axis=1, initial=0.0)
        links.loc[off, "reason"] = [
            f"not on the chain; residual against the chained map {w:.1f} sigma ({v})"
            for w, v in zip(worst, verdict, strict=True)]
    return ChainedMap(poses, links, res.reindex(columns=RESIDUAL_COLUMNS))
