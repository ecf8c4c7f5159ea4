"""Links left on no loop by failed pairs are retried in the same run (issue 16): the screened
pairs of a no-prior campaign put every link on a loop; when all but one of a scan's pairs fail,
some accepted links lie on no loop, ``retry_pairs`` lists the best pairs across them not yet
searched, and they run before the map."""

from __future__ import annotations

import pandas as pd
import pytest

from forestmap_assets.access import load_asset
from forestmap_assets.core.registration import pair_registrations
from forestmap_assets.core.registration.link_graph import bridges, sides
from forestmap_assets.io.campaign import load_campaign
from forestmap_assets.orchestration.runner import run_campaign
from forestmap_assets.outputs.exports import write_exports
from forestmap_assets.sim import simulate_campaign


@pytest.mark.slow
def test_a_scan_held_by_one_link_gets_its_pairs_retried(tmp_path, monkeypatch):
    root = simulate_campaign(tmp_path / "plot", scans=5, seed=7, resolution="quarter", plot_size=30.0, trees=30,
                             no_prior=True)
    ids = load_campaign(root).scan_ids
    weak = ids[-1]
    real = pair_registrations.register_candidates
    kept: list[tuple[str, str]] = []

    def failing(table, *args, **kwargs):
        """Every searched pair of ``weak`` but the first it is registered in fails (not the
        retried ones)."""
        out = real(table, *args, **kwargs)
        row = table.iloc[0]
        pair = (row["scan"], row["reference"])
        if weak in pair and row["source"] != "retry":
            if not kept:
                kept.append(pair)
            elif pair not in kept:
                regs = out["registrations"].copy()
                regs["status"], regs["reason"] = "rejected", "rejected by the test"
                out = {**out, "registrations": regs}
        return out

    monkeypatch.setattr(pair_registrations, "register_candidates", failing)
    summary = run_campaign(root, workers=1, progress=lambda m: None)  # in this process: the patch holds
    assert summary.failures == [] and summary.not_built == []
    candidates = load_asset("candidate_pairs", campaign=root)
    first = candidates[(candidates["scan"] == weak) | (candidates["reference"] == weak)]
    assert len(first) >= 2, first  # the screened set put the scan on a loop
    write_exports(load_campaign(root), root / "outputs", cloud_spacing_m=None, picture=False, report=False)
    regs = pd.read_csv(root / "outputs" / "registrations.csv")
    status = {(a, b): st for a, b, st in zip(regs["scan"], regs["reference"], regs["status"], strict=True)}
    searched = list(zip(candidates["scan"], candidates["reference"], strict=True))
    accepted = [p for p in searched if status[p] == "accepted"]
    assert bridges(searched) == [] and bridges(accepted), accepted  # the failures left links on no loop
    retry = load_asset("retry_pairs", campaign=root)
    assert len(retry) >= 1 and (retry["source"] == "retry").all(), retry
    for pair in zip(retry["scan"], retry["reference"], strict=True):  # each across a link on no loop
        assert pair not in searched and pair in status, pair
        assert any((pair[0] in a) != (pair[1] in a) for a, _ in (sides(accepted, b) for b in bridges(accepted)))
    retried = [p for p in zip(retry["scan"], retry["reference"], strict=True) if status[p] == "accepted"]
    assert len(bridges(accepted + retried)) < len(bridges(accepted)), (accepted, retried)
    poses = pd.read_csv(root / "outputs" / "poses.csv")
    assert poses["registered"].all(), poses
