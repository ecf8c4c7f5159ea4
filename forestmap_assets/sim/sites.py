"""The thesis's sites (spec 10.1): forest, parking lot ("outdoor") and office corridor ("indoor"),
and :func:`make_site`, which builds a structured one (the forest is
:func:`~.forest.make_forest`)."""

from __future__ import annotations

from forestmap_assets.sim.corridor import make_corridor
from forestmap_assets.sim.parking_lot import make_parking_lot
from forestmap_assets.sim.site_assembly import Site

SITES = ("forest", "parking-lot", "corridor")


SITE_ENVIRONMENT = {"forest": "forest", "parking-lot": "outdoor", "corridor": "indoor"}


def make_site(site: str, n_scans: int, size_m: float, *, seed=0, trees: int = 6, **kwargs) -> Site:
    """``corridor`` or ``parking-lot`` (the forest is :func:`~.forest.make_forest`)."""
    if site == "corridor":
        return make_corridor(n_scans, size_m, seed=seed, **kwargs)
    if site == "parking-lot":
        return make_parking_lot(n_scans, size_m, seed=seed, trees=trees, **kwargs)
    raise ValueError(f"site: expected one of {', '.join(SITES[1:])}, got {site!r}")
