"""Two campaign folders with the same ``name:`` (a folder copied to try other parameters) never
share one namespace of the asset store (issue 18): the run of the second fails with one line
naming the first; a moved folder takes its namespace along; the workspace keeps one of them."""

from __future__ import annotations

import os
import shutil
import warnings
from pathlib import Path

import pytest
from helpers.campaign_files import write_campaign

from forestmap_assets.cli import main
from forestmap_assets.io.campaign import CampaignError, load_campaign
from forestmap_assets.io.store import (
    CAMPAIGN_ROOT,
    default_store_url,
    read_campaign_root,
    recorded_elsewhere,
    write_campaign_root,
)
from forestmap_assets.orchestration.runner import run_campaign
from forestmap_assets.orchestration.workspace import build_definitions, load_campaigns


def _stored(store: Path) -> dict[str, float]:
    return {str(p): p.stat().st_mtime_ns for p in store.rglob("*.parquet")}


@pytest.mark.slow
def test_copied_folder_with_the_same_name_is_refused(tmp_path, capsys):
    a = write_campaign(tmp_path / "a", scans=("T", "S"))
    run_campaign(a, stages=["range_images"], progress=lambda m: None)
    store = Path(default_store_url())
    assert (store / "test_campaign" / CAMPAIGN_ROOT).read_text().splitlines()[0] == str(a.resolve())
    before = _stored(store)
    assert len(before) == 2

    b = tmp_path / "b"
    shutil.copytree(a, b)
    with pytest.raises(CampaignError) as info:
        run_campaign(b, stages=["range_images"], progress=lambda m: None)
    msg = str(info.value)
    assert "\n" not in msg
    assert msg == (
        f"{b / 'campaign.yaml'}: name: campaign name 'test-campaign' is already used by {a.resolve()} "
        f"(store {store}); give this folder another name: in its campaign.yaml"
    )
    capsys.readouterr()
    assert main(["run", str(b)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("forestmap: ") and "\n" not in err and f"already used by {a.resolve()}" in err
    assert _stored(store) == before  # the original's assets untouched

    # the copy renamed: its own namespace, the original's still untouched
    (b / "campaign.yaml").write_text((b / "campaign.yaml").read_text().replace("test-campaign", "test-b"))
    assert run_campaign(b, stages=["range_images"], progress=lambda m: None).failures == []
    assert _stored(store).items() >= before.items()
    assert (store / "test_b" / "range_images" / "T.parquet").exists()

    # the original moved: the record follows it, nothing to recompute
    moved = tmp_path / "moved"
    a.rename(moved)
    again = run_campaign(moved, stages=["range_images"], progress=lambda m: None)
    assert again.failures == [] and again.ran == []
    assert read_campaign_root(str(store), "test_campaign")[0] == str(moved.resolve())


def test_record_ignores_a_folder_that_left_the_name_and_a_copied_store(tmp_path):
    a = write_campaign(tmp_path / "a", scans=("T",))
    b = write_campaign(tmp_path / "b", scans=("T",))
    store = tmp_path / "store"
    write_campaign_root(str(store), "test_campaign", a)
    assert recorded_elsewhere(str(store), "test_campaign", a) is None
    assert recorded_elsewhere(str(store), "test_campaign", b) == str(a.resolve())
    # a copied store: its record came along, the copy's namespaces are its own
    shutil.copytree(store, tmp_path / "store2")
    assert recorded_elsewhere(str(tmp_path / "store2"), "test_campaign", b) is None
    # the original renamed in its campaign.yaml: the name is free (run_campaign records b)
    from forestmap_assets.orchestration.runner import claim_campaign_name

    with pytest.raises(CampaignError, match="already used by"):
        claim_campaign_name(load_campaign(b), str(store))
    (a / "campaign.yaml").write_text((a / "campaign.yaml").read_text().replace("test-campaign", "other"))
    claim_campaign_name(load_campaign(b), str(store))
    assert read_campaign_root(str(store), "test_campaign")[0] == str(b.resolve())


def test_workspace_keeps_one_campaign_per_key(tmp_path):
    data = tmp_path / "data"
    first = write_campaign(data / "a-plot", scans=("T",))
    second = write_campaign(data / "b-copy", scans=("T",))
    # the same key from another spelling of the name
    third = write_campaign(data / "c-other", scans=("T",))
    (third / "campaign.yaml").write_text((third / "campaign.yaml").read_text().replace("test-campaign", "test_campaign"))
    campaigns = load_campaigns([first, second, third])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        defs = build_definitions(campaigns)
    lines = [str(w.message) for w in caught if "already used" in str(w.message)]
    assert lines == [
        f"{second / 'campaign.yaml'}: name: campaign name 'test-campaign' is already used by {first}; "
        "this campaign is left out: give it another name: in its campaign.yaml",
        f"{third / 'campaign.yaml'}: name: campaign name 'test_campaign' (store key 'test_campaign' of "
        f"'test-campaign') is already used by {first}; this campaign is left out: give it another name: "
        "in its campaign.yaml",
    ]
    assert len(defs.resolve_asset_graph().get_all_asset_keys()) > 0  # no duplicate-key crash

    # the folder the store records as the owner of the key is the one kept
    write_campaign_root(default_store_url(), "test_campaign", second)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        build_definitions(campaigns)
    assert [str(w.message).split(":")[0] for w in caught if "already used" in str(w.message)] == [
        str(first / "campaign.yaml"),
        str(third / "campaign.yaml"),
    ]
    assert os.path.exists(Path(default_store_url()) / "test_campaign" / CAMPAIGN_ROOT)
