"""The project's home folder and the cache of scan-file digests kept in it: a scan file is hashed
once, then recognised by its size, modification time and inode (as make and rsync do), so that
a run with nothing to do does not read every scan again (issue 16)."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
from pathlib import Path

DEFAULT_HOME = "~/.forestmap"
DIGESTS = "file_digests.json"


def campaign_key(name: str) -> str:
    """A campaign name usable as a Dagster asset-key prefix and storage folder: ``[A-Za-z0-9_]+``."""
    key = re.sub(r"[^A-Za-z0-9_]", "_", name)
    return key if key and not key[0].isdigit() else f"c_{key}"


def dagster_home() -> Path:
    """The Dagster instance's folder: ``$DAGSTER_HOME``, else ``<forestmap home>/dagster``."""
    return Path(os.environ.get("DAGSTER_HOME") or forestmap_home() / "dagster")


def settled_file(dagster_folder: Path | str, key: str) -> Path:
    """Where a campaign (its :func:`campaign_key`) is recorded as settled: every stage fresh at
    the end of its last session (:mod:`forestmap_assets.orchestration.instance`)."""
    return Path(dagster_folder) / "settled" / f"{key}.txt"


def default_store_url() -> str:
    """``$FORESTMAP_STORE`` (any fsspec URL) or ``<home>/store``."""
    return os.environ.get("FORESTMAP_STORE") or str(forestmap_home() / "store")


def forestmap_home() -> Path:
    """The project's home folder: ``$FORESTMAP_HOME`` or ``~/.forestmap``."""
    return Path(os.environ.get("FORESTMAP_HOME", DEFAULT_HOME)).expanduser()


def _load(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def file_digest(path: str | os.PathLike) -> str:
    """SHA-256 (hex) of a file's content, from the home folder's cache while the file's size,
    modification time and inode are unchanged."""
    real = os.path.realpath(path)
    st = os.stat(real)
    stamp = [st.st_size, st.st_mtime_ns, st.st_ino]
    cache_path = forestmap_home() / DIGESTS
    cache = _load(cache_path)
    hit = cache.get(real)
    if hit and hit[:3] == stamp:
        return hit[3]
    h = hashlib.sha256()
    with open(real, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    digest = h.hexdigest()
    cache = _load(cache_path)  # re-read: another process may have added files meanwhile
    cache[real] = [*stamp, digest]
    with contextlib.suppress(OSError):  # a read-only home only costs the next run a re-hash
        cache_path.parent.mkdir(parents=True, exist_ok=True)
        tmp = cache_path.with_name(f".{DIGESTS}.tmp-{os.getpid()}")
        tmp.write_text(json.dumps(cache))
        os.replace(tmp, cache_path)
    return digest
