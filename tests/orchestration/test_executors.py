"""The same code on Dagster's multiprocess executor and on a Dask cluster (dagster-dask) with the
asset store on a shared fsspec URL (issue 6, DESIGN.md section 5)."""

from __future__ import annotations

import os

import pytest
from dagster import DagsterEventType
from helpers.campaign_files import write_campaign

from forestmap_assets.io.store import read_table
from forestmap_assets.orchestration.instance import get_instance
from forestmap_assets.orchestration.runner import run_campaign


def _events(instance, run_id, kind):
    return [e for e in instance.all_logs(run_id) if e.dagster_event and e.dagster_event.event_type == kind]


@pytest.mark.slow
def test_multiprocess_runs_scans_side_by_side(tmp_path):
    root = write_campaign(tmp_path / "plot", scans=("T", "S"))
    lines: list[str] = []
    summary = run_campaign(root, executor="multiprocess", workers=2, stages=["range_images"], progress=lines.append)
    assert summary.failures == []
    assert sorted(summary.ran) == [("range_images", "S"), ("range_images", "T")]
    assert any("[T] range_images" in line for line in lines) and any("[S] range_images" in line for line in lines)
    instance = get_instance()
    records = [instance.get_run_record_by_id(r) for r in summary.run_ids]
    assert len(records) == 2
    for rec in records:
        # Dagster's multiprocess executor ran the step in a child process of its own
        (worker,) = _events(instance, rec.dagster_run.run_id, DagsterEventType.STEP_WORKER_STARTED)
        (start,) = _events(instance, rec.dagster_run.run_id, DagsterEventType.STEP_START)
        assert start.dagster_event.pid != os.getpid()
    a, b = records
    assert a.start_time < b.end_time and b.start_time < a.end_time  # the two scans overlapped


@pytest.mark.slow
def test_dask_cluster_with_store_on_an_fsspec_url(tmp_path, monkeypatch):
    distributed = pytest.importorskip("dask.distributed")
    pytest.importorskip("dagster_dask")
    shared = tmp_path / "shared-store"
    monkeypatch.setenv("FORESTMAP_STORE", f"file://{shared}")
    root = write_campaign(tmp_path / "plot", scans=("T", "S"))
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        worker_pids = set(client.run(os.getpid).values())
        summary = run_campaign(root, executor="dask", dask_address=cluster.scheduler_address,
                               stages=["segments"], progress=lambda m: None)
    assert summary.failures == []
    assert sorted(summary.ran) == sorted((s, p) for s in ("range_images", "segments") for p in ("S", "T"))
    instance = get_instance()
    step_pids = {e.dagster_event.pid for r in summary.run_ids for e in _events(instance, r, DagsterEventType.STEP_START)}
    assert step_pids and step_pids <= worker_pids  # every step ran on a Dask worker
    for stage in ("range_images", "segments"):
        for scan in ("S", "T"):
            assert read_table(shared / "test_campaign" / stage / f"{scan}.parquet").num_rows > 0


def _outputs(home: str, root):
    """The campaign's stored results that do not record timings: poses, links, registrations."""
    from forestmap_assets.access import load_asset

    store = f"{home}/store"
    regs = load_asset("refined_registrations", campaign=root, store_url=store)["registrations"]
    regs = regs.drop(columns=[c for c in regs.columns if "seconds" in c]).sort_values(["scan", "reference"])
    poses = load_asset("optimal_map", campaign=root, store_url=store)["poses"]
    trees = load_asset("tree_list", campaign=root, store_url=store)
    return regs.reset_index(drop=True), poses.reset_index(drop=True), trees.reset_index(drop=True)


@pytest.mark.slow
def test_every_executor_runs_the_whole_pipeline_with_pairs_spread_over_a_cluster(tmp_path, monkeypatch):
    """Issue 17: in_process, multiprocess and a Dask LocalCluster of two worker processes give
    the same tables on a whole no-prior campaign; the pair steps ran on both Dask workers."""
    import pandas as pd

    from forestmap_assets.assets.common import PAIR_STAGES
    from forestmap_assets.sim import simulate_campaign

    distributed = pytest.importorskip("dask.distributed")
    pytest.importorskip("dagster_dask")
    root = simulate_campaign(tmp_path / "plot", scans=4, trees=14, plot_size=18.0, resolution="quarter",
                             seed=5, no_prior=True)
    results = {}
    pair_pids: set[int] = set()
    for executor in ("in_process", "multiprocess", "dask"):
        home = tmp_path / f"home-{executor}"
        monkeypatch.setenv("FORESTMAP_HOME", str(home))
        monkeypatch.setenv("DAGSTER_HOME", str(home / "dagster"))
        monkeypatch.setenv("FORESTMAP_STORE", str(home / "store"))
        if executor == "dask":
            with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                          dashboard_address=None) as cluster, distributed.Client(cluster) as client:
                workers = set(client.run(os.getpid).values())
                summary = run_campaign(root, executor="dask", dask_address=cluster.scheduler_address,
                                       progress=lambda m: None)
            instance = get_instance()
            for run_id in summary.run_ids:
                for e in _events(instance, run_id, DagsterEventType.STEP_START):
                    if any(e.dagster_event.step_key.endswith(s) for s in PAIR_STAGES):
                        pair_pids.add(e.dagster_event.pid)
            assert pair_pids <= workers
        else:
            summary = run_campaign(root, executor=executor, workers=2, progress=lambda m: None)
        assert summary.failures == [], (executor, summary.failures)
        assert {s for s, _ in summary.ran} >= {"pairwise_registrations", "refined_registrations", "tree_list"}
        results[executor] = _outputs(str(home), root)
    assert len(pair_pids) == 2  # pair steps ran on both Dask workers
    reference = results["in_process"]
    assert reference[1]["registered"].sum() >= 3
    for executor in ("multiprocess", "dask"):
        for a, b in zip(reference, results[executor], strict=True):
            pd.testing.assert_frame_equal(a, b, check_exact=False, rtol=1e-9, atol=1e-12)
