"""A second pass of ``forestmap run`` for scans found tilted (beyond the thesis; inferred).

After the map's stages, ``scan_tilts`` says which scans lean against the reference scan by more
than ``mapping.levelling_min_tilt_deg`` and ``levelling_sigmas`` sd (their campaign entries gave
no tilt, or a wrong one). :func:`level_campaign` then writes every estimated scan's tilt, composed
with the one it was levelled by, to the campaign's ``levelling.yaml``
(:mod:`forestmap_assets.io.levelling_file`); loaded again, the campaign levels those scans
accordingly, their range images change, and the run goes again from them. A scan not yet
levelled by an estimate (a new scan) is always levelled; scans already levelled are levelled
again at most until the file has seen :data:`MAX_ROUNDS` rounds: the estimate is not refined for
ever."""

from __future__ import annotations

import numpy as np

from forestmap_assets.io.campaign import Campaign
from forestmap_assets.io.levelling_file import LEVELLING_FILE, read_levelling, write_levelling

MAX_ROUNDS = 2


def tilts_to_level(campaign: Campaign, store_url: str | None):
    """The stored ``scan_tilts`` when they ask for levelling (some ``level`` true) and rounds
    are left, else None."""
    if not campaign.params.mapping.levelling:
        return None
    from forestmap_assets.access import load_asset

    try:
        tilts = load_asset("scan_tilts", campaign=campaign, store_url=store_url)
    except FileNotFoundError:
        return None
    return tilts if levelling_due(campaign, tilts) else None


def levelling_due(campaign: Campaign, tilts) -> bool:
    """Whether ``tilts`` (``scan_tilts``) ask for a levelling round: a scan to level that no
    estimate levels yet, or one that is levelled while rounds are left."""
    flagged = set(tilts.loc[tilts["level"].astype(bool), "scan"].astype(str)) if len(tilts) else set()
    if not flagged:
        return False
    if any(campaign.scan(s).levelled_from is None for s in flagged if s in campaign.scan_ids):
        return True
    _, rounds = read_levelling(campaign.root)
    return rounds < MAX_ROUNDS


def level_campaign(campaign: Campaign, tilts) -> str:
    """Write ``levelling.yaml`` for the estimated scans of ``tilts``; a one-line note."""
    from forestmap_assets.core.mapping.levelling import compose_tilt

    estimates, rounds = read_levelling(campaign.root)
    out = dict(estimates)
    for r in tilts.itertuples():
        entry = campaign.scan(r.scan)
        if not np.isfinite(r.roll_deg) or r.scan == campaign.scan_ids[0]:
            continue
        base = entry.levelled_from if entry.levelled_from is not None else entry.tilt_deg
        out[r.scan] = {"tilt_deg": compose_tilt(entry.tilt_deg, (r.roll_deg, r.pitch_deg)),
                       "from_tilt_deg": base, "sd_deg": r.sd_deg}
    write_levelling(campaign.root, campaign.scan_ids[0], out, rounds + 1)
    level = tilts[tilts["level"].astype(bool)]
    size = np.hypot(level["roll_deg"], level["pitch_deg"])
    return (f"scans {', '.join(map(str, level['scan']))} lean {size.min():.2f}-{size.max():.2f} deg against "
            f"{campaign.scan_ids[0]} (from their shared stems): levelled by {LEVELLING_FILE}, running again")
