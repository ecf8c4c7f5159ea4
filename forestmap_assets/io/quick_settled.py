"""A run with nothing to do, recognised without Dagster (issue 16: <= 3 s; importing Dagster,
building the definitions and opening the instance take about 3 s on their own).

When a ``forestmap run`` ends with every stage fresh (the session recorded the campaign as
settled) and its outputs current, the command line records a *quick key* beside the settled
record: a hash of what the run's result depends on, read without Dagster: ``campaign.yaml``
(its bytes) and ``levelling.yaml``'s, each scan file's size and modification time, the package's sources, the Dagster
instance's history (newest event, dynamic partitions, runs, read from its SQLite files), the
outputs folder's files, the store and home variables and the run's export options. The next
run computes the same key before importing anything heavy; equal means that nothing the full
check reads has changed since, and the run stops there.
Anything else (a touched scan, an edited parameter, a materialisation from the UI, a deleted
output, another forestmap version) changes the key and the run takes the full path.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

from forestmap_assets.io.home import campaign_key, dagster_home
from forestmap_assets.io.levelling_file import LEVELLING_FILE

PACKAGE = Path(__file__).resolve().parents[1]
# the home and store variables; the Dagster folder enters as the path they give (a run sets
# $DAGSTER_HOME itself, so its value differs between the end of a run and the next start)
ENV = ("FORESTMAP_HOME", "FORESTMAP_STORE")


def _stats(folder: Path, pattern: str = "*") -> list[tuple[str, int, int]]:
    out = []
    for p in sorted(folder.rglob(pattern)):
        try:
            st = p.stat()
        except OSError:
            continue
        if p.is_file():
            out.append((p.relative_to(folder).as_posix(), st.st_size, st.st_mtime_ns))
    return out


def _history(home: Path) -> tuple:
    """The Dagster history's state: newest event, dynamic partitions, runs (SQLite, read only;
    the files' own times change when the last connection closes). Raises when there is none."""
    import sqlite3

    state: list = []
    for name, queries in (
        ("history/runs/index.db", ("select max(id) from event_logs", "select count(*) from dynamic_partitions")),
        ("history/runs.db", ("select count(*), max(id), max(update_timestamp) from runs",)),
    ):
        path = home / name
        if not path.is_file():
            raise FileNotFoundError(path)
        con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
        try:
            state += [con.execute(q).fetchone() for q in queries]
        finally:
            con.close()
    return tuple(state)


def quick_key(root: Path, out: Path, options: tuple) -> tuple[str, str, dict] | None:
    """``(campaign key, quick key, campaign.yaml document)`` of campaign folder ``root`` with
    outputs in ``out``, or None when ``campaign.yaml`` cannot be read (the full run reports it)."""
    import yaml

    try:
        text = (root / "campaign.yaml").read_bytes()
        doc = yaml.safe_load(text)
        scans = doc.get("scans") or []
        paths = [str(s["path"]) for s in scans]
        files = [(p, st.st_size, st.st_mtime_ns) for p in paths for st in [(root / p).stat()]]
        home = dagster_home()
        history = _history(home)
    except Exception:
        return None
    h = hashlib.sha256(repr((str(root.resolve()), str(out.resolve()), options,
                             [os.environ.get(k) for k in ENV], str(home))).encode())
    h.update(text)
    levelling = root / LEVELLING_FILE  # the scans' estimated tilts (io/levelling_file.py)
    h.update(levelling.read_bytes() if levelling.is_file() else b"no levelling")
    for part in (files, history, _stats(PACKAGE, "*.py"), _stats(home / "settled", "*.txt"), _stats(out)):
        h.update(repr(part).encode())
    key = campaign_key(str(doc.get("name", root.name)))
    return key, h.hexdigest(), doc


def quick_file(key: str) -> Path:
    return dagster_home() / "settled" / f"{key}.quick"


def nothing_to_do(root: Path, out: Path, options: tuple) -> dict | None:
    """The campaign document when the last run left ``root`` settled with its outputs in ``out``
    and nothing has changed since; None otherwise."""
    got = quick_key(root, out, options)
    if got is None:
        return None
    key, value, doc = got
    try:
        return doc if quick_file(key).read_text() == value else None
    except OSError:
        return None


def record_settled(root: Path, out: Path, options: tuple) -> None:
    """Record the quick key of a campaign whose run just left it settled, outputs current."""
    got = quick_key(root, out, options)
    if got is None:
        return
    from forestmap_assets.io.writers import atomic_write

    key, value, _ = got
    with atomic_write(quick_file(key)) as tmp:
        tmp.write_text(value)
