"""Load every compiled kernel of forestmap from numba's disk cache up front (issue 16).

A kernel is ``@njit(cache=True)``: a process loads each signature from ``__pycache__`` at its
first call, 5-15 ms a signature. A worker's first scan paid that for every kernel of the per-scan
stages (about 0.25 s in the range image's projection alone), so it took 0.5-1.5 s longer than the
next. :func:`load_cached_kernels` loads, for every kernel module (``_*_kernels.py``), the
signatures that the cache holds for the current code and machine, and nothing else: it never
compiles. The fork server loads the serial kernels once for all its workers
(:mod:`.worker_libraries`); each worker loads the parallel ones as it starts
(:func:`~.session._init_worker`), after its numba threads have started (a parallel kernel starts
them when it is loaded, which a fork server must not do); as a first task it could go twice to
one worker and never to the other.

It reads numba's cache index through numba internals (0.6x): where they differ, nothing is
loaded and the first call of each kernel loads it, as before."""

from __future__ import annotations

import importlib
from pathlib import Path

import forestmap_assets


def kernel_modules() -> list[str]:
    """The dotted names of forestmap's kernel modules (``_*_kernels.py``)."""
    root = Path(forestmap_assets.__file__).parent
    return sorted(".".join(("forestmap_assets", *p.relative_to(root).with_suffix("").parts))
                  for p in root.rglob("_*_kernels.py"))


def load_cached_kernels(serial_only: bool = False) -> int:
    """Load every cached signature of the kernel modules' module-level kernels; returns how many
    were loaded (0 where numba's internals differ). ``serial_only``: not the ``parallel=True``
    kernels, whose loading starts numba's threads (a fork server loads the others once for all
    its workers)."""
    try:
        from numba.core.dispatcher import Dispatcher
        from numba.core.registry import cpu_target

        codegen = cpu_target.target_context.codegen()
        loaded = 0
        for name in kernel_modules():
            for kernel in vars(importlib.import_module(name)).values():
                cache = getattr(kernel, "_cache", None) if isinstance(kernel, Dispatcher) else None
                if getattr(cache, "_cache_file", None) is None:
                    continue
                if serial_only and kernel.targetoptions.get("parallel"):
                    continue
                current = cache._index_key(None, codegen)[1:]  # machine and source hash
                for key in cache._cache_file._load_index():
                    if key[1:] == current and key[0] not in kernel.overloads:  # a hit, not yet loaded
                        kernel.compile(key[0])
                        loaded += 1
        return loaded
    except Exception:  # numba's internals moved: each kernel loads at its first call instead
        return 0
