"""Virtual forest plot, structured sites and a Riegl LMS-Z210-like scanner for synthetic
campaigns with ground truth (spec 1, 10), and scoring against that truth.

May import: ``core``, ``io``, ``params``; never ``assets``, ``outputs`` or ``orchestration``.
"""

from forestmap_assets.sim.campaign import relative_pose, scan_ids, simulate_campaign
from forestmap_assets.sim.forest import Forest, make_forest
from forestmap_assets.sim.scanner import ScanPose, ScanResult, VirtualScanner
from forestmap_assets.sim.scene_mesh import SceneMesh

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
