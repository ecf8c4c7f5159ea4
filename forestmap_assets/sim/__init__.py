"""Virtual forest plot and Riegl LMS-Z210-like scanner for synthetic campaigns (spec 1, 10)."""

from .campaign import relative_pose, scan_ids, simulate_campaign
from .forest import Forest, SceneMesh, make_forest
from .scanner import ScanPose, ScanResult, VirtualScanner

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
