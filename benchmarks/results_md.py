"""The one writer of ``benchmarks/results.md``: each benchmark owns the section between
``<!-- NAME:start -->`` and ``<!-- NAME:end -->`` and replaces only that, atomically (two
benchmarks may finish at the same time)."""

from __future__ import annotations

import os
from pathlib import Path

RESULTS = Path(__file__).with_name("results.md")


def write_section(name: str, body: str, path: Path = RESULTS) -> None:
    """Replace (or append) section ``name`` of ``path`` with ``body`` (markers optional)."""
    start, end = f"<!-- {name}:start -->", f"<!-- {name}:end -->"
    body = body.strip().removeprefix(start).removesuffix(end).strip()
    block = f"{start}\n{body}\n{end}"
    old = path.read_text() if path.exists() else "# Benchmark results\n"
    if start in old and end in old:
        new = old[: old.index(start)] + block + old[old.index(end) + len(end):]
    else:
        new = old.rstrip("\n") + "\n\n" + block + "\n"
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(new)
    os.replace(tmp, path)
