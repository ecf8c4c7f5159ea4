"""A campaign of one scan is a map of one scan: no pair is searched, and the run still writes
every output (the exports used to stop at the missing pair partitions)."""

from __future__ import annotations

import pandas as pd
import pytest


@pytest.mark.slow
def test_one_scan_campaign_writes_its_outputs(tmp_path, capsys):
    from helpers.campaign_files import write_campaign

    from forestmap_assets.cli import main

    root = write_campaign(tmp_path / "plot", scans=("T",))
    assert main(["run", str(root), "--no-report", "--no-cloud"]) == 0, capsys.readouterr().err
    out = root / "outputs"
    poses = pd.read_csv(out / "poses.csv")
    assert list(poses["scan"]) == ["T"] and bool(poses["registered"].iloc[0])
    regs = pd.read_csv(out / "registrations.csv")
    assert len(regs) == 0 and "reference" in regs.columns
    assert (out / "trees.csv").exists() and (out / "elevation.npz").exists()
