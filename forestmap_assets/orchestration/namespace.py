"""One campaign folder per namespace of the asset store (and of the run history): a copied
folder that keeps the original's ``name:`` must not make the original's assets stale and replace
them (issue 18)."""

from __future__ import annotations

from pathlib import Path

from forestmap_assets.io.campaign import MANIFEST, Campaign, CampaignError, load_campaign
from forestmap_assets.io.store import recorded_elsewhere, write_campaign_root


def _name_using_key(folder: Path, key: str) -> str | None:
    """The name of the campaign in ``folder`` if its store key is ``key`` ("" when its manifest
    cannot be read: being edited, say, it still claims the key), else None."""
    if not (folder / MANIFEST).is_file():
        return None
    try:
        other = load_campaign(folder)
    except Exception:
        return ""
    return other.name if other.key == key else None


def claim_campaign_name(campaign: Campaign, store_url: str, *, record: bool = True) -> None:
    """One campaign folder per namespace of the asset store (and of the run history): a copied
    folder keeping the original's ``name:`` would make the original's assets stale and replace
    them (issue 18). Raises a one-line :class:`CampaignError` when the namespace was written
    from another folder that still holds a campaign of this key; else (``record``) records this
    folder as its owner, in ``<store>/<key>/_campaign_root.txt`` (a moved original, or a copied
    store, takes the record over)."""
    other = recorded_elsewhere(store_url, campaign.key, campaign.root)
    owner = None if other is None else _name_using_key(Path(other), campaign.key)
    if owner is not None:
        key = f" (store key {campaign.key!r} of {owner!r})" if owner and owner != campaign.name else ""
        raise CampaignError(
            f"{campaign.root / MANIFEST}: name: campaign name {campaign.name!r}{key} is already used "
            f"by {other} (store {store_url}); give this folder another name: in its {MANIFEST}"
        )
    if record:
        write_campaign_root(store_url, campaign.key, campaign.root)
