"""The ``forestmap`` command line (DESIGN.md section 3).

Every command exits 0 on success and otherwise prints one line ``forestmap: <reason>`` on
standard error and exits non-zero.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import warnings
from pathlib import Path


class UsageError(Exception):
    """A problem the user can fix; printed as one line."""


def _pair(text: str) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected M,DEG (two numbers), got {text!r}") from None
    return a, b


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="forestmap", description="Registered, checked 3-D forest maps from TLS scans.")
    p.add_argument("--quiet", "-q", action="store_true", help="print only errors and final paths")
    p.add_argument("--debug", action="store_true", help="on an error, show the traceback, not one line")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("simulate", help="write a synthetic campaign and its ground truth")
    s.add_argument("out", type=Path)
    s.add_argument("--scans", type=int, default=6)
    s.add_argument("--trees", type=int, default=40)
    s.add_argument("--plot-size", type=float, default=40.0)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--resolution", choices=["full", "half", "quarter"], default="full")
    s.add_argument("--prior-error", type=_pair, default=(1.0, 10.0), metavar="M,DEG")
    s.add_argument("--no-prior", action="store_true")
    s.add_argument("--format", choices=["npz", "las", "ply", "e57"], default="npz")
    s.add_argument("--tilt", type=_pair, default=None, metavar="ROLL,PITCH", help="max scanner tilt (deg)")

    r = sub.add_parser("run", help="materialise every asset of a campaign and write the exports")
    r.add_argument("campaign", type=Path)
    r.add_argument("--out", type=Path, default=None)
    r.add_argument("--executor", choices=["in_process", "multiprocess", "dask"], default="in_process")
    r.add_argument("--cloud-spacing", type=float, default=0.05, metavar="M",
                   help="voxel size (m) of the registered point cloud cloud.laz / cloud.ply (0: every point)")
    r.add_argument("--no-cloud", action="store_true", help="do not write cloud.laz / cloud.ply")
    r.add_argument("--no-report", action="store_true", help="do not write map.png / report.html")

    v = sub.add_parser("solve", help="optimal map and residuals from a table of pairwise observations")
    v.add_argument("observations", type=Path)
    v.add_argument("--order", default=None, help="comma separated scan order; the first is the reference")
    v.add_argument("--out", type=Path, default=None)

    st = sub.add_parser("status", help="state of each asset of a campaign")
    st.add_argument("campaign", type=Path)

    u = sub.add_parser("ui", help="start the Dagster UI on this project's workspace")
    u.add_argument("--port", type=int, default=3000)
    u.add_argument("--host", default="127.0.0.1")

    e = sub.add_parser("explore", help="plan and simulate a whole survey (next-best-view)")
    e.add_argument("out", type=Path)
    e.add_argument("--plot-size", type=float, default=40.0)
    e.add_argument("--trees", type=int, default=40)
    e.add_argument("--seed", type=int, default=0)
    e.add_argument("--budget", type=int, default=8)
    return p


def _say(args, text: str) -> None:
    if not args.quiet:
        print(text, flush=True)


def cmd_simulate(args) -> int:
    from .sim import simulate_campaign

    out = simulate_campaign(
        args.out,
        scans=args.scans,
        trees=args.trees,
        plot_size=args.plot_size,
        seed=args.seed,
        resolution=args.resolution,
        prior_error=args.prior_error,
        no_prior=args.no_prior,
        fmt=args.format,
        tilt_deg=args.tilt,
        progress=lambda m: _say(args, m),
    )
    if args.quiet:
        print(out)
    return 0


def cmd_run(args) -> int:
    from .progress import Progress, use
    from .runner import run_campaign

    if args.cloud_spacing < 0:
        raise UsageError(f"--cloud-spacing: expected a size >= 0 m, got {args.cloud_spacing:g}")
    progress = Progress(quiet=args.quiet)
    with use(progress):  # steps running in this process (in_process executor) report into it
        summary = run_campaign(args.campaign, executor=args.executor, progress=progress)
    if summary.not_built:
        _say(args, f"not yet built in this version of forestmap: {', '.join(summary.not_built)}")
    if summary.failures:
        stage, scan, reason = summary.failures[0]
        where = f"{stage}[{scan}]" if scan else stage
        more = f" (and {len(summary.failures) - 1} more failures)" if len(summary.failures) > 1 else ""
        raise UsageError(f"{where} failed: {reason}{more}")
    out = args.out or summary.campaign.root / "outputs"
    if summary.not_built:
        print(f"materialised what exists in {summary.seconds:.1f} s; no exports written to {out} yet")
        return 0
    from .exports import write_exports

    written = write_exports(summary.campaign, out, cloud_spacing_m=None if args.no_cloud else args.cloud_spacing,
                            picture=not args.no_report, report=not args.no_report, progress=progress)
    print(f"outputs written to {out}: {', '.join(p.name for p in written)}")
    _say(args, f"done in {summary.seconds:.1f} s")
    return 0


def cmd_solve(args) -> int:
    from .solve import run_solve

    order = [s.strip() for s in args.order.split(",") if s.strip()] if args.order else None
    paths = run_solve(args.observations, order=order, out_dir=args.out)
    print("written: " + ", ".join(str(p) for p in paths))
    return 0


def cmd_status(args) -> int:
    from .campaign import load_campaign
    from .definitions import build_definitions
    from .runner import get_instance, stage_states, sync_partitions

    campaign = load_campaign(args.campaign)
    defs = build_definitions([campaign])
    instance = get_instance()
    sync_partitions(instance, campaign)
    for state in stage_states(defs, campaign, instance):
        print(f"{state.stage} {state.state}")
    return 0


def cmd_ui(args) -> int:
    import subprocess

    from .runner import get_instance

    get_instance()  # sets DAGSTER_HOME to the persistent instance
    workspace = Path(__file__).resolve().parent.parent / "workspace.yaml"
    cmd = ["dagster", "dev", "-h", args.host, "-p", str(args.port)]
    if workspace.exists():
        cmd += ["-w", str(workspace)]
    else:
        cmd += ["-m", "forestmap_assets.definitions"]
    return subprocess.call(cmd)


def cmd_explore(args) -> int:
    raise UsageError("explore: next-best-view planning is not built yet in this version")


COMMANDS = {
    "simulate": cmd_simulate,
    "run": cmd_run,
    "solve": cmd_solve,
    "status": cmd_status,
    "ui": cmd_ui,
    "explore": cmd_explore,
}


def main(argv: list[str] | None = None) -> int:
    from .progress import one_line

    args = _parser().parse_args(argv)
    warnings.filterwarnings("ignore")
    logging.getLogger("dagster").setLevel(logging.WARNING)
    os.environ.setdefault("DAGSTER_DISABLE_TELEMETRY", "1")
    try:
        return COMMANDS[args.command](args)
    except KeyboardInterrupt:
        print("forestmap: interrupted", file=sys.stderr)
        return 130
    except (UsageError, ValueError, OSError) as exc:
        if args.debug:
            raise
        print(f"forestmap: {one_line(exc)}", file=sys.stderr)
        return 2
    except Exception as exc:  # anything else is still one line; --debug or FORESTMAP_DEBUG=1 shows it all
        if args.debug or os.environ.get("FORESTMAP_DEBUG"):
            raise
        print(f"forestmap: {one_line(exc)}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
