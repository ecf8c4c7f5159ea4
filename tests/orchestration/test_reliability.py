"""Reliability of runs (issue 6): two runs of one campaign at once leave one consistent store
with every asset materialised once; a failed run leaves no partial Parquet file; the CLI's idle
work never runs beside steps in this process. (A corrupt scan
failing only its own partitions: tests/orchestration/test_range_images_asset.py.)"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest
from helpers.campaign_files import write_campaign
from helpers.orchestration import edit_manifest, materialised_copy, materialised_since

from forestmap_assets.assets.common import asset_key
from forestmap_assets.io import store
from forestmap_assets.io.campaign import load_campaign
from forestmap_assets.orchestration.instance import get_instance
from forestmap_assets.orchestration.runner import campaign_lock, run_campaign
from forestmap_assets.orchestration.session import Session

RUN = (
    "import sys, warnings; warnings.filterwarnings('ignore')\n"
    "from forestmap_assets.orchestration.runner import run_campaign\n"
    "if __name__ == '__main__':\n"
    "    s = run_campaign(sys.argv[1], stages=['segments'], progress=lambda m: print(m, flush=True))\n"
    "    sys.exit(1 if s.failures else 0)\n"
)


def _files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*") if p.is_file())


@pytest.mark.slow
def test_two_runs_of_one_campaign_at_once(tmp_path):
    root = write_campaign(tmp_path / "plot", scans=("T", "S"))
    campaign = load_campaign(root)
    instance = get_instance()
    script = tmp_path / "run.py"
    script.write_text(RUN)
    logs = [tmp_path / "a.log", tmp_path / "b.log"]
    # hold the campaign's lock while both start, so that they really contend for it
    with campaign_lock(instance, campaign, lambda m: None):
        procs = [subprocess.Popen([sys.executable, str(script), str(root)], stdout=open(log, "w"),
                                  stderr=subprocess.STDOUT, env=os.environ.copy()) for log in logs]
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not all("waiting" in log.read_text() for log in logs):
            time.sleep(0.5)
        assert all("waiting" in log.read_text() for log in logs), [log.read_text() for log in logs]
    codes = [p.wait(timeout=240) for p in procs]
    assert codes == [0, 0], [log.read_text() for log in logs]
    # one of them did the work, the other found it fresh: every partition materialised once
    ran = materialised_since(instance, campaign, 0)
    assert ran == {(s, p) for s in ("range_images", "segments") for p in ("T", "S")}
    records = [
        instance.fetch_materializations(asset_key(campaign, s), limit=100).records for s in ("range_images", "segments")
    ]
    assert sum(len(r) for r in records) == 4
    files = [f for f in _files(Path(os.environ["FORESTMAP_HOME"]) / "store") if f.suffix == ".parquet"]
    assert [f.name for f in files] == ["S.parquet", "T.parquet", "S.parquet", "T.parquet"]
    for f in files:
        assert pq.read_table(f).num_rows > 0


@pytest.mark.slow
def test_failed_run_leaves_no_partial_parquet(tmp_path, monkeypatch):
    root = write_campaign(tmp_path / "plot", scans=("T", "S"))
    real = store.pq.write_table

    def half_then_fail(table, where, **kw):
        real(table.slice(0, max(1, table.num_rows // 2)), where, **kw)
        raise OSError("disk full (simulated)")

    monkeypatch.setattr(store.pq, "write_table", half_then_fail)
    # workers=1: the runs in this process, where the writer is patched
    summary = run_campaign(root, stages=["range_images"], workers=1, progress=lambda m: None)
    assert sorted((s, p) for s, p, _ in summary.failures) == [("range_images", "S"), ("range_images", "T")]
    assert all("disk full" in reason for *_, reason in summary.failures)
    images = Path(os.environ["FORESTMAP_HOME"]) / "store" / "test_campaign" / "range_images"
    assert not images.exists() or _files(images) == []  # neither a partial file nor a temporary one

    monkeypatch.setattr(store.pq, "write_table", real)
    again = run_campaign(root, stages=["range_images"], progress=lambda m: None)
    assert again.failures == [] and sorted(again.ran) == [("range_images", "S"), ("range_images", "T")]
    assert [f.name for f in _files(images)] == ["S.parquet", "T.parquet"]


def test_idle_work_only_while_the_pairs_run_in_workers():
    """Steps that run in this process import libraries; a thread importing the same ones beside
    them can see a module half initialised (``forestmap run`` on a one-scan campaign failed with
    ImportError from matplotlib.colors). The idle work waits for the pairs of several workers."""
    def session(executor, workers):
        return Session(None, None, executor, "", print, workers, None)

    two, one = {"b__a": ["pairwise_registrations"], "c__a": ["pairwise_registrations"]}, {"b__a": []}
    assert session("in_process", 2).runs_in_workers(two)
    assert session("in_process", 2).runs_in_workers(one, late={"a": ["occlusion_boundaries"]})
    assert not session("in_process", 2).runs_in_workers(one)  # one pair: here
    assert not session("in_process", 1).runs_in_workers(two)
    assert not session("multiprocess", 2).runs_in_workers(two)  # forks from this process


@pytest.mark.slow
def test_idle_work_does_not_run_beside_campaign_stages_here(tmp_path, monkeypatch):
    root = materialised_copy(tmp_path, monkeypatch)
    edit_manifest(root, params={"mapping": {"residual_sigmas": 2.5}})  # campaign-level stages only
    called = []
    summary = run_campaign(root, workers=2, progress=lambda m: None, idle=lambda: called.append(1))
    assert summary.failures == []
    assert {s for s, _ in summary.ran} and called == []
