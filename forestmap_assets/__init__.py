"""forestmap: registered, checked 3-D forest maps from terrestrial laser scans.

``load_asset`` is imported on first use (PEP 562), so that importing a light submodule (the
command line, the worker preload) does not import Dagster first."""

__all__ = ["load_asset"]


def __getattr__(name: str):
    if name == "load_asset":
        from forestmap_assets.access import load_asset

        return load_asset
    raise AttributeError(f"module 'forestmap_assets' has no attribute {name!r}")
