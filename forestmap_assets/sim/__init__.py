"""Virtual forest plot and Riegl LMS-Z210-like scanner for synthetic campaigns (spec 1, 10)."""

from forestmap_assets.sim.campaign import relative_pose, scan_ids, simulate_campaign
from forestmap_assets.sim.forest import Forest, SceneMesh, make_forest
from forestmap_assets.sim.scanner import ScanPose, ScanResult, VirtualScanner

__all__ = [
    "Forest",
    "SceneMesh",
    "ScanPose",
    "ScanResult",
    "VirtualScanner",
    "make_forest",
    "relative_pose",
    "scan_ids",
    "simulate_campaign",
]
