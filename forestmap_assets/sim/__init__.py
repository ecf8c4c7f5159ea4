"""Virtual forest plot, structured sites and a Riegl LMS-Z210-like scanner for synthetic
campaigns with ground truth (spec 1, 10), and scoring against that truth.

May import: ``core``, ``io``, ``params``; never ``assets``, ``outputs`` or ``orchestration``.

The names below are imported when first used (PEP 562), so that scoring against the truth
(:mod:`.evaluate`, the report's truth section) does not import the simulator (0.2-0.4 s on the
end of a run, issue 16).
"""

from __future__ import annotations

import importlib

_WHERE = {
    "relative_pose": "campaign",
    "scan_ids": "campaign",
    "simulate_campaign": "campaign",
    "Forest": "forest",
    "make_forest": "forest",
    "ScanPose": "scanner",
    "ScanResult": "scanner",
    "VirtualScanner": "scanner",
    "SceneMesh": "scene_mesh",
}

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


def __getattr__(name: str):
    if name in _WHERE:
        value = getattr(importlib.import_module(f"{__name__}.{_WHERE[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
