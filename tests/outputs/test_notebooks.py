"""Every notebook under notebooks/ runs top to bottom (nbclient) on a small simulated campaign.

The campaign (2 quarter-resolution scans, a small a priori search box) is simulated and
materialised once for the module in its own forestmap home; each notebook then reads it through
``$FORESTMAP_CAMPAIGN`` exactly as it reads the bundled sample after the README's main command.
"""

from __future__ import annotations

import base64
from pathlib import Path
from typing import TYPE_CHECKING

import pytest
import yaml

if TYPE_CHECKING:
    import nbformat

NOTEBOOKS = Path(__file__).resolve().parents[2] / "notebooks"


@pytest.fixture(scope="module")
def materialised(tmp_path_factory):
    from forestmap_assets.orchestration.runner import run_campaign
    from forestmap_assets.sim import simulate_campaign

    home = tmp_path_factory.mktemp("nb_home")
    env = {"FORESTMAP_HOME": str(home), "DAGSTER_HOME": str(home / "dagster")}
    with pytest.MonkeyPatch.context() as mp:
        for k, v in env.items():
            mp.setenv(k, v)
        mp.delenv("FORESTMAP_STORE", raising=False)
        folder = simulate_campaign(
            tmp_path_factory.mktemp("nb") / "plot",
            scans=2,
            trees=10,
            plot_size=12.0,
            resolution="quarter",
            prior_error=(0.15, 1.5),
            seed=3,
            write_labels=False,
        )
        manifest = yaml.safe_load((folder / "campaign.yaml").read_text())
        manifest["search"] = {"xy_m": 0.5, "z_m": 0.3, "heading_deg": 4.0}
        (folder / "campaign.yaml").write_text(yaml.safe_dump(manifest, sort_keys=False))
        summary = run_campaign(folder, progress=lambda m: None)
        assert not summary.failures, summary.failures
    return folder, env


def execute(name: str, folder: Path, env: dict, monkeypatch) -> nbformat.NotebookNode:
    # imported here, not at collection: nbformat's schema validators take ~6 s to import, and
    # every test of this module is slow (the quick loop deselects them)
    import nbformat

    nbclient = pytest.importorskip("nbclient")
    for k, v in {**env, "FORESTMAP_CAMPAIGN": str(folder)}.items():
        monkeypatch.setenv(k, v)
    book = nbformat.read(NOTEBOOKS / f"{name}.ipynb", as_version=4)
    client = nbclient.NotebookClient(
        book, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(NOTEBOOKS)}}
    )
    client.execute()  # raises CellExecutionError on the first failing cell
    return book


def outputs(book):
    for cell in book.cells:
        if cell.cell_type == "code":
            yield from cell.get("outputs", [])


def images(book) -> list[bytes]:
    return [
        base64.b64decode(o["data"]["image/png"])
        for o in outputs(book)
        if "image/png" in o.get("data", {})
    ]


def text(book) -> str:
    parts = []
    for o in outputs(book):
        if o.get("output_type") == "stream" and o.get("name") == "stdout":
            parts.append(o["text"])
        elif "text/plain" in o.get("data", {}):
            parts.append(o["data"]["text/plain"])
    return "\n".join(parts)


@pytest.mark.parametrize(
    "name, n_images", [("01_scan_features", 3), ("02_registration", 2), ("03_global_map", 6)]
)
@pytest.mark.slow
def test_reading_notebooks_run_and_draw(materialised, monkeypatch, name, n_images):
    folder, env = materialised
    book = execute(name, folder, env, monkeypatch)
    pictures = images(book)
    assert len(pictures) >= n_images
    assert all(p[:4] == b"\x89PNG" and len(p) > 5000 for p in pictures)
    assert f"campaign 'plot' in {folder}" in text(book)


@pytest.mark.slow
def test_parameters_notebook_reruns_only_downstream(materialised, monkeypatch):
    """The change here is the residual test's limit (mapping.residual_sigmas): only the stages
    reading the mapping section get a new code version, and since their outputs keep their
    content hash, nothing further downstream runs (the notebook's default change, the minimum
    cylinder length, re-runs the per-scan cylinder stages and the registration: slower, same
    code path)."""
    folder, env = materialised
    monkeypatch.setenv("FORESTMAP_CHANGE", "mapping.residual_sigmas=4.0")
    book = execute("04_parameters", folder, env, monkeypatch)
    out = text(book)

    def listed(prefix: str) -> set[str]:
        line = next(line for line in out.splitlines() if line.startswith(prefix))
        return {w.strip() for w in line[len(prefix) :].split(" in ")[0].split(",") if w.strip()}

    assert "mapping.residual_sigmas: 3.0 -> 4.0" in out
    stale, ran, kept = (
        listed("stale under the variant:"),
        listed("re-ran:"),
        listed("kept from the cache:"),
    )
    assert "optimal_map" in ran and ran <= stale  # only what Dagster called stale ran
    upstream = {
        "range_images",
        "segments",
        "circle_models",
        "cylinder_segments",
        "elevation_maps",
        "submaps",
        "candidate_pairs",
        "pairwise_registrations",
        "refined_registrations",
    }
    assert upstream <= kept
    # the variant's optimal map has the same content, so the integrated map was not rebuilt
    assert "integrated_map" in kept and "tree_list" in kept
    # back to the manifest's parameters: every stage fresh again
    final = [o for o in outputs(book) if "text/plain" in o.get("data", {})][-1]["data"][
        "text/plain"
    ]
    assert "stale" not in final and "missing" not in final and "fresh" in final
