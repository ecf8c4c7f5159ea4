"""A run with nothing to do stops before Dagster (issue 16, io/quick_settled.py): after a run that
left the campaign settled with its outputs in place, the next one says so from ``stat`` and the
history's newest event; a touched scan, an edited parameter or a deleted output takes the full path."""

from __future__ import annotations

import os

import pytest
import yaml
from helpers.orchestration import edit_manifest, materialised_copy

from forestmap_assets import cli

QUICK = "nothing changed since the last run"
ARGS = ["--no-report", "--no-cloud", "--workers", "1"]


def _run(root, capsys) -> str:
    assert cli.main(["run", str(root), *ARGS]) == 0
    return capsys.readouterr().out


@pytest.mark.slow
def test_nothing_to_do_is_recognised_and_anything_changed_is_not(tmp_path, monkeypatch, capsys):
    root = materialised_copy(tmp_path, monkeypatch)
    assert QUICK not in _run(root, capsys)  # writes the outputs, records the quick key
    out = _run(root, capsys)
    assert QUICK in out and "are up to date" in out

    scan = root / yaml.safe_load((root / "campaign.yaml").read_text())["scans"][0]["path"]
    os.utime(scan, ns=(scan.stat().st_atime_ns, scan.stat().st_mtime_ns + 10**9))
    out = _run(root, capsys)
    assert QUICK not in out and "0 to process" in out  # same content: nothing re-ran
    assert QUICK in _run(root, capsys)

    (root / "outputs" / "poses.csv").unlink()
    assert QUICK not in _run(root, capsys)
    assert (root / "outputs" / "poses.csv").is_file()

    edit_manifest(root, params={"cylinders": {"min_length_m": 3.0}})
    out = _run(root, capsys)
    assert QUICK not in out and "cylinder_segments" in out
    assert QUICK in _run(root, capsys)
