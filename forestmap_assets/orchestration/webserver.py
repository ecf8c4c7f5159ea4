"""Starting the Dagster UI on this project's workspace and talking to its GraphQL API
(``forestmap ui``, the webserver test and ``scripts/screenshot_lineage.py``)."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
WORKSPACE = REPO / "workspace.yaml"

ASSETS_QUERY = """
{
  assetNodes {
    assetKey { path }
    groupName
    description
    assetChecksOrError { ... on AssetChecks { checks { name } } }
  }
}
"""


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def webserver_command(host: str, port: int, dev: bool = False) -> list[str]:
    """``dagster-webserver`` (UI only) or ``dagster dev`` (UI + daemon for sensors, schedules
    and automation) on ``workspace.yaml``, else on the ``forestmap_assets.orchestration.definitions`` module."""
    bindir = Path(sys.executable).parent
    cmd = [str(bindir / "dagster"), "dev"] if dev else [str(bindir / "dagster-webserver")]
    cmd += ["-h", host, "-p", str(port)]
    cmd += ["-w", str(WORKSPACE)] if WORKSPACE.exists() else ["-m", "forestmap_assets.orchestration.definitions"]
    return cmd


def start_webserver(host: str = "127.0.0.1", port: int | None = None, env: dict | None = None,
                    log=subprocess.DEVNULL) -> tuple[subprocess.Popen, str]:
    """Start the webserver in its own process group on the persistent instance (created if
    needed, see :func:`forestmap_assets.orchestration.instance.get_instance`); returns the process and its URL."""
    from forestmap_assets.orchestration.instance import get_instance

    get_instance()  # sets $DAGSTER_HOME when unset and makes sure the folder exists
    port = port or free_port(host)
    environ = {**os.environ, "DAGSTER_DISABLE_TELEMETRY": "1", **(env or {})}
    proc = subprocess.Popen(webserver_command(host, port), cwd=REPO, env=environ, stdout=log,
                            stderr=subprocess.STDOUT, start_new_session=True)
    return proc, f"http://{host}:{port}"


def wait_ready(proc: subprocess.Popen, url: str, timeout_s: float = 120.0) -> None:
    """Poll ``/server_info`` until the webserver answers (bounded in time)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"the webserver exited with code {proc.returncode} before it was ready")
        try:
            with urllib.request.urlopen(f"{url}/server_info", timeout=5) as r:
                if r.status == 200:
                    return
        except (urllib.error.URLError, ConnectionError, TimeoutError):
            pass
        time.sleep(1.0)
    raise TimeoutError(f"the webserver at {url} did not answer within {timeout_s:.0f} s")


def stop(proc: subprocess.Popen, timeout_s: float = 20.0) -> None:
    """Stop the webserver's process group (only the group this module started)."""
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout_s)


def graphql(url: str, query: str, variables: dict | None = None, timeout_s: float = 60.0) -> dict:
    body = json.dumps({"query": query, "variables": variables or {}}).encode()
    req = urllib.request.Request(f"{url}/graphql", data=body, headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(req, timeout=timeout_s) as r:
        out = json.loads(r.read())
    if out.get("errors"):
        raise RuntimeError(f"GraphQL errors: {out['errors']}")
    return out["data"]


def assets_and_checks(url: str) -> dict[str, list[str]]:
    """``{asset key "a/b": [check names]}`` as the running UI sees them."""
    nodes = graphql(url, ASSETS_QUERY)["assetNodes"]
    return {
        "/".join(n["assetKey"]["path"]): sorted(c["name"] for c in (n.get("assetChecksOrError") or {}).get("checks", []))
        for n in nodes
    }
