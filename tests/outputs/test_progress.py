"""Command-line progress: messages, bars (or their plain stand-ins), quiet mode, one-line errors."""

from __future__ import annotations

import io

from forestmap_assets.outputs.progress import Progress, as_progress, one_line, report, use


class Tty(io.StringIO):
    def isatty(self):
        return True


def test_plain_lines_without_a_terminal():
    out = io.StringIO()
    p = Progress(stream=io.StringIO(), out=out)
    assert not p.bars
    p("starting")
    with p.bar(3, "scans") as bar:
        for sid in "TSR":
            bar.update(note=sid)
    assert out.getvalue().splitlines() == [
        "starting",
        "  scans 1/3: T",
        "  scans 2/3: S",
        "  scans 3/3: R",
    ]


def test_bars_on_a_terminal_and_messages_above_them():
    err, out = Tty(), io.StringIO()
    p = Progress(stream=err, out=out)
    assert p.bars
    with p.bar(2, "exports", unit="file") as bar:
        p("a message")
        bar.update(note="poses.csv")
        bar.update(note="trees.csv")
        assert bar._tqdm.n == 2
    assert "a message" in out.getvalue()  # printed above the bar, not into it
    assert "exports: 0/2" in err.getvalue() and "a message" not in err.getvalue()
    assert bar._tqdm is None  # closed (and cleared: leave=False)


def test_quiet_prints_nothing():
    err, out = Tty(), io.StringIO()
    p = Progress(quiet=True, stream=err, out=out)
    p("hello")
    with p.bar(2, "scans") as bar:
        bar.update()
    with use(p):
        report("pair 1/2: S-T 1.0 s")
    assert err.getvalue() == "" and out.getvalue() == ""


def test_counted_messages_from_a_step_drive_a_bar():
    out = io.StringIO()
    p = Progress(stream=io.StringIO(), out=out)
    report("pair 1/9: S-T")  # nothing current: ignored
    with use(p):
        report("pair 1/2: S-T 1.2 s")
        assert [b.desc for b in p._open] == ["pairs"]
        report("pair 2/2: R-T 0.8 s")
        assert p._open == []  # closed at k = n
        report("a plain message")
    assert out.getvalue().splitlines() == [
        "  pairs 1/2: S-T 1.2 s",
        "  pairs 2/2: R-T 0.8 s",
        "    a plain message",
    ]


def test_as_progress_wraps_plain_callables():
    seen = []
    p = as_progress(seen.append)
    p("one")
    with p.bar(2, "scans") as bar:
        bar.update()
    assert seen == ["one"]  # a plain callback gets messages, not per-step lines
    assert as_progress(p) is p
    as_progress(None)("silent")


def test_one_line_errors():
    assert one_line(ValueError("bad value\nmore detail")) == "bad value"
    assert one_line(KeyError("T")) == "missing 'T'"
    assert one_line(RuntimeError("")) == "RuntimeError"
    assert one_line(RuntimeError("\n  boom  \n")) == "RuntimeError: boom"
