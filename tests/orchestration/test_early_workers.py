"""`forestmap run` starts the workers' fork server before it imports Dagster only when the run
will likely use workers (issue 16): several scans, the in_process executor, more than one
worker, and not a campaign left settled with no file touched since (a no-op run)."""

from __future__ import annotations

import argparse
import os
import time

import pytest

from forestmap_assets import cli
from forestmap_assets.orchestration import forkserver


@pytest.fixture
def started(monkeypatch, tmp_path):
    calls = []
    monkeypatch.setattr(forkserver, "start", lambda: calls.append(True))
    monkeypatch.setenv("DAGSTER_HOME", str(tmp_path / "dagster"))
    return calls


def _campaign(tmp_path, n_scans: int, name: str = "plot 7"):
    root = tmp_path / f"camp{n_scans}"
    (root / "scans").mkdir(parents=True)
    lines = [f"name: {name}", "scans:"]
    for i in range(n_scans):
        (root / "scans" / f"s{i}.ply").write_text("ply\n")
        lines.append(f"- {{id: s{i}, path: scans/s{i}.ply}}")
    (root / "campaign.yaml").write_text("\n".join(lines) + "\n")
    return root


def _args(root, **kw):
    return argparse.Namespace(**{"executor": "in_process", "workers": 2, "campaign": str(root), **kw})


def test_starts_for_a_campaign_of_several_scans(started, tmp_path):
    cli._start_workers_early(_args(_campaign(tmp_path, 3)))
    assert started == [True]


@pytest.mark.parametrize("kw", [{"workers": 1}, {"executor": "dask"}, {"executor": "multiprocess"}])
def test_not_without_in_process_workers(started, tmp_path, kw):
    cli._start_workers_early(_args(_campaign(tmp_path, 3), **kw))
    assert started == []


def test_not_for_one_scan_or_a_bad_campaign(started, tmp_path):
    cli._start_workers_early(_args(_campaign(tmp_path, 1)))
    cli._start_workers_early(_args(tmp_path / "missing"))
    bad = _campaign(tmp_path, 2)
    (bad / "campaign.yaml").write_text("scans: [: broken\n")
    cli._start_workers_early(_args(bad))
    assert started == []


def test_settled_campaign_untouched_since_is_left_alone(started, tmp_path):
    root = _campaign(tmp_path, 3)
    settled = tmp_path / "dagster" / "settled" / "plot_7.txt"  # Campaign.key of "plot 7"
    settled.parent.mkdir(parents=True)
    settled.write_text("key")
    later = time.time() + 10
    os.utime(settled, (later, later))
    cli._start_workers_early(_args(root))
    assert started == []
    os.utime(root / "scans" / "s1.ply", (later + 5, later + 5))  # a scan changed since
    cli._start_workers_early(_args(root))
    assert started == [True]


def test_campaign_key_is_the_one_of_the_campaign():
    from forestmap_assets.io.home import campaign_key

    assert campaign_key("plot 7") == "plot_7"
    assert campaign_key("2024-plot") == "c_2024_plot"


def test_worker_libraries_leave_out_open3ds_plotly_viewer():
    """The fork server's libraries: Open3D works (the refinement clouds' normals) without Dash and
    plotly, which its package would import for its plotly viewer (0.3-0.5 s of the start-up)."""
    import subprocess
    import sys

    code = (
        "import sys, numpy as np\n"
        "import forestmap_assets.orchestration.worker_libraries\n"
        "from forestmap_assets.core.registration.two_way import sensor_normals\n"
        "n = sensor_normals(np.random.default_rng(0).normal(size=(200, 3)) * [1, 1, 0.01] + [0, 0, -1], 10)\n"
        "print(sorted({'dash', 'plotly'} & set(sys.modules)), bool(np.all(n[:, 2] > 0.9)))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["[]", "True"]


def test_leaving_removes_the_fork_servers_socket_folder(tmp_path):
    """`_leave` ends the process with ``os._exit``, which skips multiprocessing's own clean-up
    of its ``pymp-*`` folder: every run left one in the temporary directory."""
    import subprocess
    import sys

    code = (
        "import multiprocessing.util as u\n"
        "from forestmap_assets.orchestration import forkserver\n"
        "from forestmap_assets import cli\n"
        "forkserver.start()\n"
        f"assert u.get_temp_dir().startswith({str(tmp_path)!r})\n"
        "cli._leave(0)\n"
    )
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert not list(tmp_path.glob("pymp-*"))


def test_the_tree_lists_range_image_columns_are_read_ahead(tmp_path, monkeypatch):
    """Before a campaign-level run in this process, the per-scan tables its later stages read
    column by column (the tree list's range images) start reading in the background."""
    import types

    from forestmap_assets.io.campaign import load_campaign
    from forestmap_assets.io.store import ParquetIOManager
    from forestmap_assets.orchestration.session import Session
    from forestmap_assets.orchestration.workspace import build_definitions

    campaign = load_campaign(_campaign(tmp_path, 2))
    store_url = str(tmp_path / "store")
    calls = []
    monkeypatch.setattr(ParquetIOManager, "read_ahead", lambda self, *a: calls.append(a))
    session = types.SimpleNamespace(executor="in_process", campaign=campaign, store_url=store_url,
                                    defs=build_definitions([campaign], store_url, executor="in_process"))
    Session.read_ahead(session, ["scan_tilts", "integrated_map", "tree_list"])
    reads = {path[-1]: (path, list(scans), set(columns)) for path, scans, columns in calls}
    assert len(reads) == len(calls) and "range_images" in reads
    path, scans, columns = reads["range_images"]
    assert path == [campaign.key, "range_images"] and scans == ["s0", "s1"]
    assert {"x", "y", "z"} <= columns and "intensity" not in columns
    assert all(scans == ["s0", "s1"] and columns for _, scans, columns in reads.values())
    session.executor = "multiprocess"  # each step in its own process: nothing to read ahead here
    Session.read_ahead(session, ["tree_list"])
    assert len(calls) == len(reads)


def test_a_bad_campaign_is_reported_before_dagster_is_imported(tmp_path):
    """A missing campaign folder, a scan file that is not there or a bad option stops `forestmap
    run` with its one-line error before Dagster and the stages are imported (a second sooner)."""
    import subprocess
    import sys

    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "campaign.yaml").write_text("name: bad\nscans: [{id: a, path: a.ply}, {id: b, path: b.ply}]\n")
    code = (
        "import sys\n"
        "from forestmap_assets.cli import main\n"
        "rc = main(sys.argv[1:])\n"
        "print(rc, 'dagster' in sys.modules, 'forestmap_assets.orchestration.runner' in sys.modules)\n"
    )
    env = {**os.environ, "FORESTMAP_HOME": str(tmp_path / "home"), "TMPDIR": str(tmp_path)}
    for argv, said in (
        ([str(tmp_path / "nowhere")], "campaign folder does not exist"),
        ([str(bad)], "scans[0].path: file not found: a.ply"),
        ([str(bad), "--cloud-spacing", "-1"], "--cloud-spacing: expected a size >= 0 m"),
    ):
        done = subprocess.run([sys.executable, "-c", code, "run", *argv], env=env, capture_output=True,
                              text=True, timeout=120)
        assert done.stdout.split() == ["2", "False", "False"], (argv, done.stdout, done.stderr)
        assert said in done.stderr
