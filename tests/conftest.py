"""Shared test fixtures: every test gets its own forestmap home and Dagster instance."""

from __future__ import annotations

import warnings

import pytest


@pytest.fixture(autouse=True)
def _isolated_home(tmp_path_factory, monkeypatch):
    home = tmp_path_factory.mktemp("forestmap_home")
    monkeypatch.setenv("FORESTMAP_HOME", str(home))
    monkeypatch.setenv("DAGSTER_HOME", str(home / "dagster"))
    monkeypatch.delenv("FORESTMAP_STORE", raising=False)
    monkeypatch.delenv("FORESTMAP_CAMPAIGNS", raising=False)
    warnings.filterwarnings("ignore", module="dagster")
    yield home
