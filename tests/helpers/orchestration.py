"""Shared fixtures of the orchestration tests: one small simulated campaign materialised once per
test session (template), copied into each test's own folder, and counting what actually ran.

The template: a 3-scan quarter-resolution virtual forest whose manifest lists only T and S (R is
there to be added by a test). Copying the campaign with its forestmap home (store + Dagster
instance) gives each test a fully materialised campaign without paying for it again.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import shutil
import tempfile
import warnings
from pathlib import Path

import yaml
from dagster import AssetRecordsFilter, DagsterInstance

from forestmap_assets.assets.common import PIPELINE, asset_key
from forestmap_assets.io.campaign import Campaign, load_campaign

_TEMPLATE: dict[str, Path] = {}


@contextlib.contextmanager
def environ(**values: str):
    old = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def two_of_three(manifest: dict) -> dict:
    """The simulated manifest restricted to scans T and S."""
    keep = {"T", "S"}
    doc = dict(manifest)
    doc["scans"] = [s for s in manifest["scans"] if s["id"] in keep]
    doc["pairs"] = [p for p in manifest.get("pairs", []) if {p["scan"], p["reference"]} <= keep]
    return doc


def template() -> Path:
    """Build (once per session) and return the materialised template folder."""
    if "root" in _TEMPLATE:
        return _TEMPLATE["root"]
    from forestmap_assets.orchestration.runner import run_campaign
    from forestmap_assets.sim import simulate_campaign

    base = Path(tempfile.mkdtemp(prefix="forestmap-orch-"))
    atexit.register(shutil.rmtree, base, True)
    plot = simulate_campaign(base / "plot", scans=3, trees=10, plot_size=16.0, resolution="quarter", seed=3)
    full = yaml.safe_load((plot / "campaign.yaml").read_text())
    (plot / "full_manifest.yaml").write_text(yaml.safe_dump(full, sort_keys=False))
    write_manifest(plot, two_of_three(full))
    home = base / "home"
    with environ(FORESTMAP_HOME=str(home), DAGSTER_HOME=str(home / "dagster")), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        summary = run_campaign(plot, progress=lambda m: None)
    assert summary.failures == [], summary.failures
    _TEMPLATE["root"] = base
    return base


def materialised_copy(tmp_path: Path, monkeypatch) -> Path:
    """A private copy of the materialised template; returns the campaign folder."""
    dst = tmp_path / "t"
    shutil.copytree(template(), dst)
    monkeypatch.setenv("FORESTMAP_HOME", str(dst / "home"))
    monkeypatch.setenv("DAGSTER_HOME", str(dst / "home" / "dagster"))
    return dst / "plot"


def write_manifest(root: Path, doc: dict) -> None:
    (root / "campaign.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))


def edit_manifest(root: Path, **changes) -> dict:
    doc = yaml.safe_load((root / "campaign.yaml").read_text())
    doc.update(changes)
    write_manifest(root, doc)
    return doc


def cursor(instance: DagsterInstance) -> int:
    return instance.event_log_storage.get_maximum_record_id() or 0


def materialised_since(instance: DagsterInstance, campaign: Campaign, after: int) -> set[tuple[str, str | None]]:
    """(stage, partition) of every materialisation of the campaign's assets after ``after``,
    read from the instance's event log (what Dagster actually ran)."""
    out = set()
    for stage, _ in PIPELINE:
        records = instance.fetch_materializations(
            AssetRecordsFilter(asset_key=asset_key(campaign, stage), after_storage_id=after), limit=10_000
        ).records
        out |= {(stage, r.asset_materialization.partition) for r in records}
    return out


def status_lines(root: Path, capsys) -> dict[str, str]:
    """``forestmap status ROOT`` as {asset: state}."""
    from forestmap_assets.cli import main

    capsys.readouterr()
    assert main(["status", str(root)]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    pairs = [line.split() for line in lines]
    prefix = load_campaign(root).key + "/"
    assert all(key.startswith(prefix) for key, _ in pairs), lines  # `<asset_key> <state>`
    return {key[len(prefix):]: state for key, state in pairs}


def campaign(root: Path) -> Campaign:
    return load_campaign(root)


def data_versions(defs, root: Path) -> dict[tuple[str, str | None], str]:
    """Current data version of every (stage, partition) of the campaign."""
    from forestmap_assets.orchestration.instance import get_instance
    from forestmap_assets.orchestration.status import _resolver, campaign_stages, partitions_of

    c = load_campaign(root)
    instance = get_instance()
    resolver = _resolver(defs, instance)
    return {
        (stage, part): resolver.get_current_data_version(asset_key(c, stage), part).value
        for stage, g in campaign_stages(defs, c)
        for part in partitions_of(instance, c, g)
    }


def inputs_of(defs, root: Path, stage: str, part: str | None) -> list[tuple[str, str | None]]:
    """The (stage, partition) inputs of one asset partition."""
    from forestmap_assets.assets.common import split_pair_key
    from forestmap_assets.assets.pairs import PAIR_LISTS, PAIR_SCAN_INPUTS
    from forestmap_assets.orchestration.instance import get_instance
    from forestmap_assets.orchestration.status import campaign_stages, partitions_of, stage_parents

    c = load_campaign(root)
    granularity = dict(campaign_stages(defs, c))
    parents = list(stage_parents(defs, c)[stage])
    if granularity[stage] == "pair":  # a pair step also reads its scans' outputs and its row
        parents += [s for s in (*PAIR_SCAN_INPUTS, *PAIR_LISTS) if s in granularity]

    def parts(p: str) -> list[str | None]:
        if granularity[p] == granularity[stage]:
            return [part]
        if granularity[stage] == "pair" and granularity[p] == "scan":
            return list(split_pair_key(part, c.scan_ids))
        return partitions_of(get_instance(), c, granularity[p])

    return [(p, q) for p in parents for q in parts(p)]
