"""The map's files before the where-to-scan-next stages (issue 16): ``run_campaign`` calls
``map_ready`` once the map stages are done and next_vantage_points has not run yet; with workers
it then runs beside the caller (in a worker), with one process after it."""

from __future__ import annotations

import pytest
from helpers.orchestration import edit_manifest, materialised_copy

from forestmap_assets.orchestration.runner import run_campaign


@pytest.mark.slow
@pytest.mark.parametrize(("workers", "params"), [
    (2, {"trees": {"dbh_method": "cylinders"}}),  # a new tree list
    (1, {"trees": {"dbh_method": "cylinders"}}),
    # new sigmas, a new integrated map: its readers tree_list and next_vantage_points fall due
    # together, and the tree list still goes first
    (2, {"mapping": {"scale_sd_floor": 5e-4}}),
])
def test_map_ready_comes_before_next_vantage_points(tmp_path, monkeypatch, workers, params):
    root = materialised_copy(tmp_path, monkeypatch)
    edit_manifest(root, params=params)
    seen = []

    def map_ready(summary):
        seen.append({s for s, _ in summary.ran})

    lines = []
    summary = run_campaign(root, progress=lines.append, workers=workers, map_ready=map_ready)
    assert summary.failures == []
    assert len(seen) == 1, seen
    assert "tree_list" in seen[0] and "next_vantage_points" not in seen[0]
    assert "next_vantage_points" in {s for s, _ in summary.ran}
    beside = any("beside the map's files" in line for line in lines)
    assert beside == (workers > 1), lines
    # nothing of the map ran again: no second call
    seen.clear()
    assert run_campaign(root, progress=lambda m: None, map_ready=map_ready).ran == []
    assert seen == []


@pytest.mark.slow
def test_occlusion_boundaries_wait_for_the_map_with_one_worker(tmp_path, monkeypatch):
    """Without workers to leave them running in, the scans' where-to-scan-next stage runs after
    the map's stages, not before them (issue 16: it never delays the map)."""
    root = materialised_copy(tmp_path, monkeypatch)
    edit_manifest(root, params={"trees": {"dbh_method": "cylinders"}, "occlusion": {"alpha_thr_deg": 6.0}})
    seen = []
    summary = run_campaign(root, progress=lambda m: None, workers=1,
                           map_ready=lambda s: seen.append({stage for stage, _ in s.ran}))
    assert summary.failures == []
    assert len(seen) == 1 and "tree_list" in seen[0]
    assert "occlusion_boundaries" not in seen[0], seen
    ran = [stage for stage, _ in summary.ran]
    assert "occlusion_boundaries" in ran and ran.index("tree_list") < ran.index("occlusion_boundaries")


def test_the_map_files_thread_raises_its_error_where_the_session_waits():
    """runner._Writer: the map's files written in a thread while scans' where-to-scan-next runs
    end (issue 16); its error is not lost in the thread but raised by ``finish``."""
    import threading

    from forestmap_assets.orchestration.runner import _Writer

    names = []
    _Writer(lambda s: names.append((s, threading.current_thread().name)), "summary").finish()
    assert names == [("summary", "map-files")]

    def fails(summary):
        raise OSError("outputs: read-only")

    writer = _Writer(fails, None)
    with pytest.raises(OSError, match="read-only"):
        writer.finish()
