"""The lineage dashboard: the Dagster webserver on this project's workspace, on loopback, serves
every asset and asset check of the definitions through its GraphQL API (issue 6)."""

from __future__ import annotations

import pytest
from helpers.campaign_files import write_campaign

from forestmap_assets.orchestration.automation import automated_definitions
from forestmap_assets.orchestration.webserver import (
    assets_and_checks,
    start_webserver,
    stop,
    wait_ready,
)
from forestmap_assets.orchestration.workspace import (
    discover_campaign_folders,
    load_campaigns,
)


@pytest.mark.slow
def test_webserver_serves_every_asset_and_check(tmp_path, monkeypatch):
    data = tmp_path / "data"
    write_campaign(data / "plot", scans=("T", "S"))
    monkeypatch.setenv("FORESTMAP_DATA_ROOT", str(data))
    defs = automated_definitions(load_campaigns(discover_campaign_folders()))
    graph = defs.resolve_asset_graph()
    expected: dict[str, list[str]] = {k.to_user_string(): [] for k in graph.get_all_asset_keys()}
    for check in graph.asset_check_keys:
        expected[check.asset_key.to_user_string()].append(check.name)
    expected = {k: sorted(v) for k, v in expected.items()}
    assert "test_campaign/tree_list" in expected
    assert "admitted_links_consistent" in expected["test_campaign/residual_checks"]

    log = open(tmp_path / "webserver.log", "w")
    proc, url = start_webserver(log=log)
    try:
        wait_ready(proc, url, timeout_s=150)
        seen = assets_and_checks(url)
    finally:
        stop(proc)
        log.close()
    assert seen == expected, (tmp_path / "webserver.log").read_text()[-3000:]
