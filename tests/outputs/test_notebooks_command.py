"""``forestmap notebooks CAMPAIGN``: the Jupyter Lab command line and environment it would use
(the launcher is replaced, no server starts), and its one-line error without Jupyter Lab."""

from __future__ import annotations

import os
import sys
import tomllib
from pathlib import Path

import pytest

from forestmap_assets import cli
from forestmap_assets.orchestration import notebook

REPO = Path(__file__).resolve().parents[2]
SAMPLE = REPO / "data" / "sample"


@pytest.fixture
def launched(monkeypatch):
    """Calls of the launcher, which returns 0 at once instead of starting Jupyter Lab."""
    calls = []

    def fake_launch(argv, env, cwd):
        calls.append((list(argv), dict(env), Path(cwd)))
        return 0

    monkeypatch.setattr(notebook, "launch", fake_launch)
    monkeypatch.setattr(notebook, "jupyterlab_installed", lambda: True)
    return calls


def test_starts_jupyter_lab_in_notebooks_on_the_campaign(launched, monkeypatch, capsys):
    monkeypatch.chdir(REPO)  # a relative campaign path becomes absolute
    monkeypatch.setenv("FORESTMAP_TEST_KEEP", "kept")
    assert cli.main(["notebooks", "data/sample", "--port", "8899", "--no-browser"]) == 0
    [(argv, env, cwd)] = launched
    assert argv[:3] == [sys.executable, "-m", "jupyterlab"]  # the same environment's Jupyter
    assert f"--ServerApp.root_dir={REPO / 'notebooks'}" in argv
    assert "--port=8899" in argv and "--no-browser" in argv
    assert cwd == REPO / "notebooks"
    assert env["FORESTMAP_CAMPAIGN"] == str(SAMPLE)
    assert Path(env["FORESTMAP_CAMPAIGN"]).is_absolute()
    assert env["FORESTMAP_TEST_KEEP"] == "kept"  # the rest of the environment passes through
    assert "FORESTMAP_CAMPAIGN=" in capsys.readouterr().out


def test_defaults_leave_port_and_browser_to_jupyter(launched):
    assert cli.main(["notebooks", str(SAMPLE)]) == 0
    [(argv, _, _)] = launched
    assert not any(a.startswith("--port") for a in argv)
    assert "--no-browser" not in argv


@pytest.mark.parametrize("uid", [0, 1000])
def test_root_is_allowed_only_when_running_as_root(monkeypatch, uid):
    monkeypatch.setattr(os, "geteuid", lambda: uid, raising=False)
    argv, _, _ = notebook.lab_command(SAMPLE)
    assert ("--allow-root" in argv) == (uid == 0)


def test_the_notebooks_find_the_campaign_the_command_sets(monkeypatch, tmp_path):
    _, env, _ = notebook.lab_command(SAMPLE)
    monkeypatch.chdir(tmp_path)  # not in the repository: only the variable can point there
    monkeypatch.setenv(notebook.CAMPAIGN_VARIABLE, env[notebook.CAMPAIGN_VARIABLE])
    assert notebook.campaign_folder() == SAMPLE


def test_without_jupyterlab_one_line_error_and_exit_2(monkeypatch, capsys):
    calls = []
    monkeypatch.setattr(notebook, "launch", lambda *a: calls.append(a) or 0)
    monkeypatch.setitem(sys.modules, "jupyterlab", None)  # find_spec then reports it missing
    assert not notebook.jupyterlab_installed()
    assert cli.main(["notebooks", str(SAMPLE)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert err.startswith("forestmap: Jupyter Lab is not installed")
    assert "pip install jupyterlab" in err
    assert not calls


def test_a_folder_that_is_no_campaign_is_refused(launched, tmp_path, capsys):
    assert cli.main(["notebooks", str(tmp_path)]) == 2
    assert "campaign" in capsys.readouterr().err
    assert not launched


def test_setup_installs_jupyterlab():
    """scripts/setup.sh installs the dev extra; it must bring Jupyter Lab along."""
    extras = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    for extra in ("dev", "notebooks"):
        assert any(req.split(">")[0].split("=")[0].strip() == "jupyterlab" for req in extras[extra])
