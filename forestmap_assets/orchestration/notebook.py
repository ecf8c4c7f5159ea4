"""Small helpers for the notebooks under ``notebooks/``.

The notebooks read their campaign folder from ``$FORESTMAP_CAMPAIGN`` and otherwise use the
bundled sample ``data/sample`` (after the README's main command ``forestmap run data/sample``
its assets are in the store). They read every stage's output straight from the asset store with
:func:`~forestmap_assets.access.load_asset`. ``forestmap notebooks CAMPAIGN`` starts Jupyter Lab
in ``notebooks/`` with that variable set (:func:`lab_command`).
"""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

import pandas as pd

from forestmap_assets.core.geometry import relative_pose
from forestmap_assets.io.campaign import Campaign

SAMPLE = Path("data") / "sample"
CAMPAIGN_VARIABLE = "FORESTMAP_CAMPAIGN"
NOTEBOOKS = Path(__file__).resolve().parents[2] / "notebooks"
INSTALL_HINT = (
    "Jupyter Lab is not installed in this environment; install it with "
    f"{Path(sys.executable).parent / 'pip'} install jupyterlab (or: bash scripts/setup.sh)"
)


def campaign_folder(default: str | os.PathLike | None = None) -> Path:
    """``$FORESTMAP_CAMPAIGN`` if set; else ``default``; else the repository's ``data/sample``,
    looked for from the working directory upwards (a notebook runs in ``notebooks/``) and next
    to the installed package."""
    env = os.environ.get(CAMPAIGN_VARIABLE)
    if env:
        return Path(env).expanduser().resolve()
    if default is not None:
        return Path(default).expanduser().resolve()
    here = Path.cwd().resolve()
    for folder in (here, *here.parents, Path(__file__).resolve().parents[2]):
        if (folder / SAMPLE / "campaign.yaml").is_file():
            return folder / SAMPLE
    raise FileNotFoundError(
        "no campaign: set FORESTMAP_CAMPAIGN to a campaign folder, or run the README's main "
        "command (forestmap run data/sample) from the repository"
    )


def jupyterlab_installed() -> bool:
    """Whether Jupyter Lab can be started from this Python environment."""
    return importlib.util.find_spec("jupyterlab") is not None


def lab_command(
    campaign: str | os.PathLike, port: int | None = None, no_browser: bool = False
) -> tuple[list[str], dict[str, str], Path]:
    """Command line, environment and working folder that start Jupyter Lab on the notebooks
    under ``notebooks/`` for ``campaign``: this interpreter's ``-m jupyterlab`` (with
    ``--allow-root`` when run as root), with ``$FORESTMAP_CAMPAIGN`` set to the campaign
    folder's absolute path."""
    argv = [sys.executable, "-m", "jupyterlab", f"--ServerApp.root_dir={NOTEBOOKS}"]
    if port is not None:
        argv.append(f"--port={port}")
    if no_browser:
        argv.append("--no-browser")
    if hasattr(os, "geteuid") and os.geteuid() == 0:
        argv.append("--allow-root")  # containers run as root; Jupyter refuses it otherwise
    env = {**os.environ, CAMPAIGN_VARIABLE: str(Path(campaign).expanduser().resolve())}
    return argv, env, NOTEBOOKS


def launch(argv: list[str], env: dict[str, str], cwd: Path) -> int:
    """Run ``argv`` in ``cwd`` with ``env`` until it ends; its exit status. A Ctrl-C on the
    terminal reaches Jupyter Lab too, which shuts itself down (kernels included), so this
    waits for it rather than killing it."""
    import subprocess

    proc = subprocess.Popen(argv, env=env, cwd=cwd)
    while True:
        try:
            return proc.wait()
        except KeyboardInterrupt:
            continue


def truth_poses(campaign: Campaign) -> pd.DataFrame | None:
    """``truth/poses.csv`` of a simulated campaign (``scan, x, y, z, heading_deg``), else None."""
    path = campaign.root / "truth" / "poses.csv"
    return pd.read_csv(path, dtype={"scan": str}) if path.is_file() else None


def truth_relative(
    campaign: Campaign, scan: str, reference: str
) -> tuple[float, float, float, float] | None:
    """True location of ``scan`` in the levelled frame of ``reference`` (simulated campaigns)."""
    truth = truth_poses(campaign)
    if truth is None:
        return None
    t = truth.set_index("scan")
    if scan not in t.index or reference not in t.index:
        return None
    cols = ["x", "y", "z", "heading_deg"]
    return relative_pose(t.loc[scan, cols].to_numpy(float), t.loc[reference, cols].to_numpy(float))


def variant_campaign(
    campaign: Campaign, overrides: dict[str, dict], folder: str | os.PathLike
) -> Path:
    """A copy of the campaign's manifest in ``folder`` with the same name (so the same asset
    keys, store and cache) and scan paths pointing at the original files, with ``overrides``
    merged into its ``params`` section. Returns the new campaign folder."""
    import yaml

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    doc = yaml.safe_load((campaign.root / "campaign.yaml").read_text())
    doc["name"] = campaign.name
    for scan in doc["scans"]:
        scan["path"] = str((campaign.root / scan["path"]).resolve())
    params = dict(doc.get("params") or {})
    for stage, values in overrides.items():
        params[stage] = {**dict(params.get(stage) or {}), **values}
    doc["params"] = params
    (folder / "campaign.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    return folder


def stage_table(campaign: Campaign) -> pd.Series:
    """State (``missing`` / ``stale`` / ``fresh``) of every pipeline stage of ``campaign``
    under its own manifest, from Dagster's stale-status resolver (as ``forestmap status``)."""
    from forestmap_assets.orchestration.definitions import build_definitions
    from forestmap_assets.orchestration.instance import get_instance
    from forestmap_assets.orchestration.status import stage_states

    states = stage_states(build_definitions([campaign]), campaign, get_instance())
    return pd.Series({s.stage: s.state for s in states}, name="state")
