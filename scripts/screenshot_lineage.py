"""Screenshot of the Dagster UI's lineage view of a campaign, for the README.

Starts the webserver on loopback on this project's workspace (campaigns under
``$FORESTMAP_DATA_ROOT``, default ``data/``; run history from ``$DAGSTER_HOME`` or the forestmap
home, so materialise the campaign first to see its statuses), waits for it, and lets headless
Chromium (Debian's ``chromium`` package) render the lineage page::

    forestmap run data/sample
    python scripts/screenshot_lineage.py --out docs/lineage.png

Exits non-zero with a one-line reason when Chromium or the webserver is missing or fails.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from forestmap_assets.orchestration.webserver import REPO, start_webserver, stop, wait_ready

CHROMIUM_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
    "--disable-component-update", "--disable-sync", "--no-first-run", "--hide-scrollbars",
]


def screenshot(url: str, out: Path, width: int, height: int, wait_ms: int) -> None:
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        raise SystemExit("screenshot_lineage: chromium not found (apt-get install -y chromium)")
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as profile:
        cmd = [browser, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", f"--window-size={width},{height}",
               f"--virtual-time-budget={wait_ms}", f"--screenshot={out}", url]
        subprocess.run(cmd, check=True, timeout=wait_ms / 1000 + 120,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    if not out.is_file():
        raise SystemExit(f"screenshot_lineage: chromium wrote no {out}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=REPO / "docs" / "lineage.png")
    p.add_argument("--campaign", default="sample", help="campaign key whose lineage to show")
    p.add_argument("--path", default=None, help="UI page to render instead (e.g. /asset-groups)")
    p.add_argument("--width", type=int, default=1800)
    p.add_argument("--height", type=int, default=1100)
    p.add_argument("--wait-ms", type=int, default=25000, help="virtual time for the page to render")
    args = p.parse_args(argv)
    proc, url = start_webserver()
    try:
        wait_ready(proc, url, timeout_s=180)
        # the lineage around the optimal map reaches every stage, from scan files to tree list
        path = args.path or f"/assets/{args.campaign}/optimal_map?view=lineage&lineageScope=neighbors&lineageDepth=12"
        screenshot(f"{url}{path}", args.out, args.width, args.height, args.wait_ms)
    finally:
        stop(proc)
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
