"""Stage timings tell work from waiting (issue 16): each step records its seconds and the CPU
seconds of its thread, and the report's timing table sums both per stage."""

from __future__ import annotations

import time

import numpy as np
import pytest
from dagster import Output
from helpers.orchestration import materialised_copy

from forestmap_assets.assets.common import timed
from forestmap_assets.io.campaign import load_campaign
from forestmap_assets.orchestration.timings import stage_timings


def _spin(seconds: float) -> None:
    """Work until this thread has used ``seconds`` of CPU (however busy the machine is)."""
    end = time.thread_time() + seconds
    while time.thread_time() < end:
        pass


def test_timed_records_seconds_and_the_threads_cpu_seconds():
    @timed
    def waits():
        time.sleep(0.3)
        return Output(1, metadata={"kept": 2})

    @timed
    def works():
        _spin(0.3)
        yield Output(1)

    meta = waits().metadata
    assert meta["kept"].value == 2
    assert meta["seconds"].value >= 0.3 and meta["cpu_seconds"].value < 0.1  # asleep: no CPU
    meta = next(works()).metadata
    assert meta["cpu_seconds"].value >= 0.29 and meta["cpu_seconds"].value <= meta["seconds"].value + 0.01


@pytest.mark.slow
def test_stage_timings_sum_cpu_seconds_per_stage(tmp_path, monkeypatch):
    t = stage_timings(load_campaign(materialised_copy(tmp_path, monkeypatch))).set_index("stage")
    done = t[t["outputs"] > 0]
    assert len(done) >= 10
    cpu, secs = done["cpu_seconds"].to_numpy(float), done["seconds"].to_numpy(float)
    assert np.isfinite(cpu).all() and (cpu > 0).any()
    assert (cpu <= secs + 0.02 * t.loc[done.index, "outputs"].to_numpy()).all()
    assert t.loc["range_images", "cpu_seconds"] > 0
