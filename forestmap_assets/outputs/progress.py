"""Progress reporting for the command line: messages, progress bars for long steps, quiet mode.

:class:`Progress` is a callable ``progress(message)`` (what
:func:`~forestmap_assets.orchestration.runner.run_campaign` already accepts) with bars on top:
``with progress.bar(n, "scans") as bar: ... bar.update(note=sid)``.
Bars are drawn with tqdm on standard error when it is a terminal, and replaced by one line per
finished step otherwise (logs stay readable); ``quiet`` silences both.

Code running inside a Dagster step of the same process (the in-process executor) reports
through :func:`report`, which reaches the :class:`Progress` made current by :func:`use`, if any,
and otherwise does nothing: e.g. ``register_candidates(..., progress=report)`` turns its
``"pair 3/6: S-T 2.1 s"`` messages into a bar.
"""

from __future__ import annotations

import re
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TextIO

_COUNTER = re.compile(
    r"^\s*(?P<what>[A-Za-z_ -]+?)\s+(?P<k>\d+)\s*/\s*(?P<n>\d+)\s*:?\s*(?P<note>.*)$"
)


class Bar:
    """One progress bar (tqdm) or its plain-text stand-in."""

    def __init__(self, owner: Progress, total: int | None, desc: str, unit: str):
        self.owner, self.total, self.desc, self.unit = owner, total, desc, unit
        self.done = 0
        self.closed = False
        self.start = time.perf_counter()
        self._tqdm = None
        if owner.enabled and owner.bars:
            from tqdm.auto import tqdm

            self._tqdm = tqdm(
                total=total,
                desc=desc,
                unit=unit,
                file=owner.stream,
                leave=False,
                dynamic_ncols=True,
                bar_format="{desc}: {n_fmt}/{total_fmt} {bar} {elapsed}<{remaining}{postfix}",
            )

    def update(self, n: int = 1, note: str = "") -> None:
        """Advance by ``n`` steps; ``note`` names what just finished. No-op once closed."""
        if self.closed:
            return
        self.done += n
        if self._tqdm is not None:
            if note:
                self._tqdm.set_postfix_str(note, refresh=False)
            self._tqdm.update(n)
        elif self.owner.enabled and self.owner.step_lines:
            total = f"/{self.total}" if self.total else ""
            self.owner.write(f"  {self.desc} {self.done}{total}{': ' + note if note else ''}")

    def set(self, k: int, total: int | None = None, note: str = "") -> None:
        """Move to ``k`` done (of ``total``)."""
        if total is not None and total != self.total:
            self.total = total
            if self._tqdm is not None:
                self._tqdm.total = total
        self.update(max(k - self.done, 0), note)

    def close(self) -> None:
        self.closed = True
        if self._tqdm is not None:
            self._tqdm.close()
            self._tqdm = None

    @property
    def seconds(self) -> float:
        return time.perf_counter() - self.start


class Progress:
    """Messages and progress bars for the command line (see the module docstring).

    ``quiet``: nothing is shown. ``bars``: draw tqdm bars (default: when ``stream`` is a
    terminal). ``step_lines``: without bars, print one line per finished step."""

    def __init__(
        self,
        *,
        quiet: bool = False,
        stream: TextIO | None = None,
        bars: bool | None = None,
        step_lines: bool = True,
        out: TextIO | None = None,
    ):
        self.enabled = not quiet
        self.stream = stream if stream is not None else sys.stderr
        self.out = out if out is not None else sys.stdout
        self.bars = bool(self.stream.isatty()) if bars is None else bars
        self.step_lines = step_lines
        self._open: list[Bar] = []

    def __call__(self, message: str) -> None:
        """Print a message line (above any open bar)."""
        if self.enabled:
            self.write(message)

    def write(self, message: str) -> None:
        if self._open and self.bars:
            from tqdm.auto import tqdm

            tqdm.write(message, file=self.out)
        else:  # one write under a lock: lines from the workers' drain thread stay whole
            with _WRITE_LOCK:
                self.out.write(message + "\n")
                self.out.flush()

    @contextmanager
    def bar(self, total: int | None, desc: str, unit: str = "step") -> Iterator[Bar]:
        """A progress bar for a long step with ``total`` parts."""
        bar = Bar(self, total, desc, unit)
        self._open.append(bar)
        try:
            yield bar
        finally:
            bar.close()
            self._open.remove(bar)

    def steps(self, items, desc: str, unit: str = "step", note: Callable[[object], str] = str):
        """Iterate over ``items`` with a bar (advanced after each item)."""
        items = list(items)
        with self.bar(len(items), desc, unit) as bar:
            for item in items:
                yield item
                bar.update(note=note(item))

    def counter(self, message: str) -> bool:
        """Feed a ``"<what> k/n: note"`` message to a bar named ``<what>``s (opened at k=1,
        closed at k=n); return False when the message has no counter."""
        m = _COUNTER.match(message)
        if not m:
            return False
        what, k, n, note = m["what"].strip(), int(m["k"]), int(m["n"]), m["note"]
        desc = what if what.endswith("s") else what + "s"
        bar = next((b for b in self._open if b.desc == desc), None)
        if bar is None:
            bar = Bar(self, n, desc, what)
            self._open.append(bar)
        bar.set(k, n, note)
        if k >= n:
            bar.close()
            self._open.remove(bar)
        return True

    def close(self) -> None:
        for bar in list(self._open):
            bar.close()
        self._open.clear()


def as_progress(progress: Callable[[str], None] | Progress | None) -> Progress:
    """A :class:`Progress` for any callback: a Progress is returned as is, ``None`` gives a
    quiet one, a plain callable (e.g. ``print``) gets messages with no bars."""
    if isinstance(progress, Progress):
        return progress
    if progress is None:
        return Progress(quiet=True)
    return _Callback(progress)


class _Callback(Progress):
    def __init__(self, fn: Callable[[str], None]):
        super().__init__(bars=False, step_lines=False)
        self._fn = fn

    def write(self, message: str) -> None:
        self._fn(message)


_CURRENT: list[Progress] = []
_WRITE_LOCK = threading.Lock()


@contextmanager
def use(progress: Progress) -> Iterator[Progress]:
    """Make ``progress`` the target of :func:`report` (for code running in this process)."""
    _CURRENT.append(progress)
    try:
        yield progress
    finally:
        _CURRENT.remove(progress)


def report(message: str) -> None:
    """Progress from inside a pipeline step: counted messages (``"pair 3/6: ..."``) advance a
    bar of the current :class:`Progress`; others are printed when steps are shown. No-op when
    nothing is current (another process, or no command line)."""
    if not _CURRENT:
        return
    p = _CURRENT[-1]
    if not p.enabled:
        return
    if not p.counter(message) and p.step_lines:
        p.write(f"    {message}")


def one_line(exc: BaseException) -> str:
    """An exception as one line: its first non-empty message line, else its type name; types
    that are not the user's to fix (not ValueError / OSError / KeyError) are prefixed with
    their name."""
    text = next((line.strip() for line in str(exc).splitlines() if line.strip()), "")
    if isinstance(exc, KeyError) and text.startswith("'") and text.endswith("'"):
        text = f"missing {text}"
    if not text:
        return type(exc).__name__
    if isinstance(exc, (ValueError, OSError, KeyError)) or type(exc).__name__ in (
        "UsageError",
        "CampaignError",
    ):
        return text
    return f"{type(exc).__name__}: {text}"
