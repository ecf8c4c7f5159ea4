"""forestmap: registered, checked 3-D forest maps from terrestrial laser scans."""

from forestmap_assets.access import load_asset

__all__ = ["load_asset"]
