"""The ``forestmap`` command line (DESIGN.md section 3).

Every command exits 0 on success and otherwise prints one line ``forestmap: <reason>`` on
standard error and exits non-zero.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys
import time
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
    # the same two flags after the sub-command (``forestmap run DIR --quiet``); SUPPRESS keeps
    # the top-level value when they are not repeated there
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--quiet", "-q", action="store_true", default=argparse.SUPPRESS,
                        help="print only errors and final paths")
    common.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                        help="on an error, show the traceback, not one line")
    sub = p.add_subparsers(dest="command", required=True)

    def command(name: str, help: str) -> argparse.ArgumentParser:
        return sub.add_parser(name, help=help, parents=[common])

    s = command("simulate", "write a synthetic campaign and its ground truth")
    s.add_argument("out", type=Path)
    s.add_argument("--scans", type=int, default=6)
    s.add_argument("--trees", type=int, default=40)
    s.add_argument("--plot-size", type=float, default=40.0)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--resolution", choices=["fine", "full", "half", "quarter"], default="full")
    s.add_argument("--prior-error", type=_pair, default=(1.0, 10.0), metavar="M,DEG")
    s.add_argument("--no-prior", action="store_true")
    s.add_argument("--format", choices=["npz", "las", "ply", "e57", "e57-multi"], default="npz",
                   help="e57-multi: one E57 holding every scan with its pose (tilt, rough heading and "
                   "position from --prior-error), as scanner software exports a day")
    s.add_argument("--project-frame", action="store_true",
                   help="las/ply points in a UTM-like project frame, each scan's pose in campaign.yaml")
    s.add_argument("--tilt", type=_pair, default=None, metavar="ROLL,PITCH", help="max scanner tilt (deg)")
    s.add_argument("--site", choices=["forest", "parking-lot", "corridor"], default="forest",
                   help="the thesis's sites (spec 10.1): forest plot, parking lot (environment outdoor) "
                   "or office corridor (environment indoor); --plot-size is the lot / corridor ring size")
    s.add_argument("--people", type=int, default=0, help="people-shaped occluders (parking lot, corridor)")
    s.add_argument("--stems", choices=["circular", "realistic"], default="circular",
                   help="realistic: out-of-round, fluted, rough, swept and forked stems, dead branches, "
                   "dense understorey (forest site)")
    s.add_argument("--colour", action="store_true",
                   help="RGB per point: bark, foliage, ground and clutter colours under each scan's light "
                   "(Men 2012 2.3), for hue-assisted ICP")

    r = command("run", "materialise every asset of a campaign and write the exports")
    r.add_argument("campaign", type=Path)
    r.add_argument("--out", type=Path, default=None)
    r.add_argument("--executor", choices=["in_process", "multiprocess", "dask"], default="in_process")
    r.add_argument("--workers", type=int, default=None,
                   help="worker processes for the scans' and pairs' runs, or of the local Dask cluster "
                   "(default: CPU count; 1 with in_process: one run after another in this process)")
    r.add_argument("--dask-address", default=None,
                   help="Dask scheduler (default: $FORESTMAP_DASK_ADDRESS, else a local cluster)")
    r.add_argument("--cloud-spacing", type=float, default=0.05, metavar="M",
                   help="voxel size (m) of the registered point cloud cloud.laz / cloud.ply (0: every point)")
    r.add_argument("--no-cloud", action="store_true", help="do not write cloud.laz / cloud.ply")
    r.add_argument("--no-report", action="store_true", help="do not write map.png / report.html")

    v = command("solve", "optimal map and residuals from a table of pairwise observations")
    v.add_argument("observations", type=Path)
    v.add_argument("--order", default=None, help="comma separated scan order; the first is the reference")
    v.add_argument("--out", type=Path, default=None)

    st = command("status", "state of each asset of a campaign")
    st.add_argument("campaign", type=Path)
    st.add_argument("--detail", action="store_true",
                    help="also one line per scan and per pair partition, and counts per state")

    u = command("ui", "start the Dagster UI on this project's workspace")
    u.add_argument("--port", type=int, default=3000)
    u.add_argument("--host", default="127.0.0.1")

    i = command("init", "write a campaign.yaml for a folder of scan files or a multi-scan E57")
    i.add_argument("source", type=Path, metavar="FOLDER_OR_E57")
    i.add_argument("--out", type=Path, default=None, help="campaign folder (default: the folder / the E57's)")
    i.add_argument("--force", action="store_true", help="replace an existing campaign.yaml")

    nb = command("notebooks", "open the notebooks under notebooks/ in Jupyter Lab on a campaign")
    nb.add_argument("campaign", type=Path)
    nb.add_argument("--port", type=int, default=None, help="Jupyter Lab's port (default: its own, 8888)")
    nb.add_argument("--no-browser", action="store_true", help="print the address; do not open a browser")

    e = command("explore", "plan and simulate a whole survey (next-best-view)")
    e.add_argument("out", type=Path)
    e.add_argument("--plot-size", type=float, default=40.0)
    e.add_argument("--trees", type=int, default=40)
    e.add_argument("--seed", type=int, default=0)
    e.add_argument("--budget", type=int, default=8, help="largest number of scans (default 8)")
    e.add_argument("--resolution", choices=["full", "half", "quarter"], default="full")
    e.add_argument("--min-gain", type=float, default=0.01,
                   help="stop when a scan adds less than this share of the plot (default 0.01)")
    return p


def _say(args, text: str) -> None:
    if not args.quiet:
        print(text, flush=True)


def cmd_simulate(args) -> int:
    from forestmap_assets.sim import simulate_campaign
    from forestmap_assets.sim.scanner_exports import pack_e57, place_in_project_frame

    multi = args.format == "e57-multi"
    if args.project_frame and args.format not in ("las", "ply"):
        raise UsageError("--project-frame: only with --format las or ply")
    out = simulate_campaign(
        args.out,
        scans=args.scans,
        trees=args.trees,
        plot_size=args.plot_size,
        seed=args.seed,
        resolution=args.resolution,
        prior_error=args.prior_error,
        no_prior=args.no_prior,
        fmt="npz" if multi or args.project_frame else args.format,
        tilt_deg=args.tilt,
        progress=lambda m: _say(args, m),
        site=args.site,
        site_kwargs={"people": args.people} if args.people else None,
        scanner_kwargs={"colour": True} if args.colour else None,
        stems=args.stems,
    )
    if multi:
        path = pack_e57(out, prior_error=args.prior_error, seed=args.seed, with_prior=not args.no_prior)
        _say(args, f"scans packed into {path} with their poses")
    elif args.project_frame:
        place_in_project_frame(out, args.format)
        _say(args, f"scans written as {args.format} in a project frame, poses in campaign.yaml")
    if args.quiet:
        print(out)
    return 0


def cmd_init(args) -> int:
    from forestmap_assets.io.campaign_init import init_campaign

    manifest, found = init_campaign(args.source, args.out, force=args.force)
    files = sorted({f.path for f in found})
    _say(args, f"found {len(found)} scans in {len(files)} file{'s' if len(files) != 1 else ''}:")
    for f in found:
        where = f.path + (f"  (E57 scan {f.e57_scan})" if f.e57_scan is not None else "")
        points = f", {f.points} points" if f.points is not None else ""
        _say(args, f"  {f.id}: {where}{points}" + "".join(f"; {n}" for n in f.notes))
    _say(args, f"wrote {manifest} (check environment: and the ids, then: forestmap run "
         f"{manifest.parent})")
    if args.quiet:
        print(manifest)
    return 0


def _start_workers_early(args) -> None:
    """Start the worker processes' fork server before this process imports Dagster (issue 16:
    both import side by side; the workers then fork ready), when the run will likely use
    workers: the in_process executor, more than one worker, more than one scan (or an E57 file,
    which may hold several), and not a campaign whose last session left it settled with no file
    touched since (likely nothing to do: the server would only slow that run down). Anything
    unclear: leave it to the run."""
    if args.executor != "in_process" or (args.workers or os.cpu_count() or 1) < 2:
        return
    try:
        import yaml

        from forestmap_assets.io.home import campaign_key, dagster_home, settled_file

        root = Path(args.campaign)
        doc = yaml.safe_load((root / "campaign.yaml").read_text())
        scans = doc.get("scans") or []
        paths = [str(s.get("path", "") if isinstance(s, dict) else s) for s in scans]
        if len(paths) < 2 and not any(p.lower().endswith(".e57") for p in paths):
            return
        settled = settled_file(dagster_home(), campaign_key(str(doc.get("name", root.name))))
        if settled.exists():
            files = [root / "campaign.yaml", *(root / p for p in paths)]
            if settled.stat().st_mtime > max(f.stat().st_mtime for f in files if f.exists()):
                return
    except Exception:  # a bad campaign is reported by the run, with its file and field
        return
    from forestmap_assets.orchestration import forkserver

    forkserver.start()


def _quick_options(args) -> tuple:
    return (None if args.no_cloud else args.cloud_spacing, not args.no_report)


def _nothing_to_do(args, started: float) -> bool:
    """A campaign settled by its last run, nothing changed since, outputs in place: say so and
    stop before Dagster is imported (:mod:`forestmap_assets.io.quick_settled`)."""
    from forestmap_assets.io.home import dagster_home, default_store_url
    from forestmap_assets.io.quick_settled import nothing_to_do

    root = Path(args.campaign)
    out = Path(args.out) if args.out else root / "outputs"
    doc = nothing_to_do(root, out, _quick_options(args))
    if doc is None:
        return False
    n = len(doc.get("scans") or [])
    _say(args, f"{doc.get('name', root.name)}: {n} scans, 0 to process, {n} up to date")
    print(f"outputs in {out} are up to date")
    _say(args, f"asset store: {default_store_url()}; run history: {dagster_home()} (forestmap ui)")
    _say(args, f"done in {time.perf_counter() - started:.1f} s (nothing changed since the last run)")
    return True


def cmd_run(args) -> int:
    started = time.perf_counter()
    if args.cloud_spacing < 0:
        raise UsageError(f"--cloud-spacing: expected a size >= 0 m, got {args.cloud_spacing:g}")
    if args.executor != "dask" and _nothing_to_do(args, started):
        return 0
    _start_workers_early(args)
    from forestmap_assets.io.campaign import load_campaign

    load_campaign(args.campaign)  # a bad campaign says so now, not after Dagster's import (1 s)
    from forestmap_assets.orchestration.runner import run_campaign
    from forestmap_assets.outputs.progress import Progress, use

    progress = Progress(quiet=args.quiet)
    options = {"cloud": None if args.no_cloud else args.cloud_spacing, "report": not args.no_report}
    early: list[Path] = []  # the map's files, written before the where-to-scan-next stages end
    loaded: dict = {}  # the assets those files read, for the report after them

    def map_ready(summary) -> None:
        if summary.not_built or _level_failure(summary):
            return
        from forestmap_assets.outputs.exports import write_exports

        out = args.out or summary.campaign.root / "outputs"
        early.extend(write_exports(summary.campaign, out, cloud_spacing_m=options["cloud"],
                                   picture=not args.no_report, progress=progress, map_only=True,
                                   stored=loaded, pieces=options["report"]))  # the report's figures too
        _say(args, f"map written to {out}: {', '.join(p.name for p in early)}"
             + ("; where to scan next follows" if options["report"] else ""))

    with use(progress):  # steps running in this process (in_process executor) report into it
        summary = run_campaign(args.campaign, executor=args.executor, progress=progress,
                               workers=args.workers, dask_address=args.dask_address,
                               idle=None if args.no_report else _warm_exports, map_ready=map_ready)
    ran = time.perf_counter()
    if summary.not_built:
        _say(args, f"not yet built in this version of forestmap: {', '.join(summary.not_built)}")
    # a campaign-level or pair stage failed (a failed scan is left out, below)
    if failure := _level_failure(summary):
        stage, scan, reason = failure
        where = f"{stage}[{scan}]" if scan else stage
        more = f" (and {len(summary.failures) - 1} more failures)" if len(summary.failures) > 1 else ""
        raise UsageError(f"{where} failed: {reason}{more}")
    out = args.out or summary.campaign.root / "outputs"
    if summary.not_built:
        print(f"materialised what exists in {summary.seconds:.1f} s; no exports written to {out} yet")
        return _left_out(summary)
    from forestmap_assets.orchestration.instance import get_instance
    from forestmap_assets.orchestration.status import latest_materialization_id
    from forestmap_assets.orchestration.timings import stage_timings_or_note
    from forestmap_assets.outputs.exports import (
        exports_current,
        exports_key,
        write_exports,
        write_exports_stamp,
    )

    key = exports_key(summary.campaign, latest_materialization_id(get_instance(), summary.campaign), options)
    if exports_current(out, key):
        print(f"outputs in {out} are up to date")
    else:
        timings = None if args.no_report else stage_timings_or_note(summary.campaign)
        if not early:
            written = write_exports(summary.campaign, out, cloud_spacing_m=options["cloud"],
                                    picture=not args.no_report, report=not args.no_report,
                                    progress=progress, timings=timings)
        else:  # the map's files are written: the report is what is left
            from forestmap_assets.outputs.report import write_report

            written = early if args.no_report else [
                *early, write_report(summary.campaign, out, timings=timings, stored=loaded)]
        write_exports_stamp(out, key, written)
        print(f"outputs written to {out}: {', '.join(p.name for p in written)}")
    if summary.check_failures:
        _say(args, f"{len(summary.check_failures)} asset checks failed (listed above)")
    from forestmap_assets.io.store import default_store_url

    _say(args, f"asset store: {default_store_url()}; run history: {os.environ.get('DAGSTER_HOME')} (forestmap ui)")
    now = time.perf_counter()
    _say(args, f"done in {now - started:.1f} s (stages {summary.seconds:.1f} s, exports {now - ran:.1f} s)")
    code = _left_out(summary)
    if code == 0 and summary.settled and not summary.check_failures:
        from forestmap_assets.io.quick_settled import record_settled

        record_settled(Path(args.campaign), Path(out), _quick_options(args))
    return code


def _warm_exports() -> None:
    """The libraries of map.png and report.html, imported while this process waits for the
    pairs (about 1.5 s of the exports otherwise), and matplotlib's fonts loaded by one small
    figure (the campaign-level stages' pictures and the exports draw text)."""
    import pyvista.plotting  # noqa: F401

    import forestmap_assets.outputs.render  # noqa: F401
    import forestmap_assets.outputs.report  # noqa: F401
    from forestmap_assets.outputs.figures.common import new_figure, png_bytes

    fig = new_figure(1.0, 1.0)
    fig.subplots().set_title("0.1 m")
    png_bytes(fig, dpi=20)


def _level_failure(summary) -> tuple | None:
    """The first failure of a campaign-level or pair stage (a failed scan is left out)."""
    ids = set(summary.campaign.scan_ids)
    return next((f for f in summary.failures if f[1] not in ids), None)


def _left_out(summary) -> int:
    """Exit code of a run that wrote its outputs: 3, with one line on standard error naming the
    scan and its file, when it left a scan out (unreadable or damaged file; DESIGN section 3)."""
    left = summary.left_out
    if not left:
        return 0
    scan, reason = next(iter(left.items()))
    what = ("not updated (outputs use its earlier results)" if scan in summary.kept_earlier
            else "left out of the outputs")
    more = f" (also left out: {', '.join(list(left)[1:])})" if len(left) > 1 else ""
    print(f"forestmap: scan {scan} {what}: {reason}{more}", file=sys.stderr)
    return 3


def cmd_solve(args) -> int:
    from forestmap_assets.outputs.solve import run_solve

    order = [s.strip() for s in args.order.split(",") if s.strip()] if args.order else None
    paths = run_solve(args.observations, order=order, out_dir=args.out)
    print("written: " + ", ".join(str(p) for p in paths))
    return 0


def cmd_status(args) -> int:
    from forestmap_assets.io.campaign import load_campaign
    from forestmap_assets.orchestration.instance import get_instance, sync_partitions
    from forestmap_assets.orchestration.status import stage_states
    from forestmap_assets.orchestration.workspace import build_definitions

    campaign = load_campaign(args.campaign)
    defs = build_definitions([campaign])
    instance = get_instance()
    sync_partitions(instance, campaign)
    from forestmap_assets.assets.common import asset_key

    for state in stage_states(defs, campaign, instance):
        name = asset_key(campaign, state.stage).to_user_string()
        print(f"{name} {state.state}")
        if args.detail and state.granularity != "campaign":
            print(f"  {state.counts()}")
            for part, value in state.per_partition.items():
                print(f"  {name}[{part}] {value}")
    return 0


def cmd_ui(args) -> int:
    import subprocess

    from forestmap_assets.orchestration.instance import get_instance
    from forestmap_assets.orchestration.webserver import webserver_command
    from forestmap_assets.orchestration.workspace import data_root

    get_instance()  # sets DAGSTER_HOME to the persistent instance
    _say(args, f"Dagster UI on http://{args.host}:{args.port} for the campaigns under {data_root()} "
               "(sensors, schedule and automation run with it; Ctrl-C stops it)")
    return subprocess.call(webserver_command(args.host, args.port, dev=True))


def cmd_notebooks(args) -> int:
    from forestmap_assets.io.campaign import load_campaign
    from forestmap_assets.orchestration import notebook

    campaign = load_campaign(args.campaign)  # a clear error for a folder that is no campaign
    if not notebook.NOTEBOOKS.is_dir():
        raise UsageError(f"no notebooks folder at {notebook.NOTEBOOKS} (it comes with the repository)")
    if not notebook.jupyterlab_installed():
        raise UsageError(notebook.INSTALL_HINT)
    argv, env, cwd = notebook.lab_command(campaign.root, port=args.port, no_browser=args.no_browser)
    _say(args, f"Jupyter Lab on {cwd} with {notebook.CAMPAIGN_VARIABLE}={env[notebook.CAMPAIGN_VARIABLE]} "
               "(Ctrl-C stops it)")
    return notebook.launch(argv, env, cwd)


def cmd_explore(args) -> int:
    from forestmap_assets.explore.planned_survey import explore

    if args.budget < 1:
        raise UsageError("explore: --budget must be at least 1")
    res = explore(args.out, plot_size=args.plot_size, trees=args.trees, seed=args.seed,
                  budget=args.budget, resolution=args.resolution, min_gain=args.min_gain,
                  progress=lambda m: _say(args, m))
    _say(args, f"explore: {len(res.steps)} scans ({res.stop_reason}); coverage "
               f"{100 * res.coverage:.1f} %, {res.trees_with_dbh} trees with DBH; "
               f"steps in {res.folder / 'explore' / 'steps.csv'}, map in {res.folder / 'outputs'}")
    if args.quiet:
        print(res.folder)
    return 0


COMMANDS = {
    "simulate": cmd_simulate,
    "run": cmd_run,
    "solve": cmd_solve,
    "status": cmd_status,
    "ui": cmd_ui,
    "init": cmd_init,
    "notebooks": cmd_notebooks,
    "explore": cmd_explore,
}


def main(argv: list[str] | None = None) -> int:
    from forestmap_assets.outputs.progress import one_line

    if argv is None:  # the console script: leave without tearing 2,000 modules down (1 s)
        _leave(main(sys.argv[1:]))
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


def _remove_multiprocessing_tempdir() -> None:
    """The ``pymp-*`` folder multiprocessing made in the temporary directory for the fork
    server's socket: its own clean-up runs at the interpreter's exit, which ``os._exit`` skips,
    so every run left one behind. The fork server stops by itself when this process ends."""
    if "multiprocessing" not in sys.modules:
        return
    import multiprocessing.process
    import shutil

    tempdir = multiprocessing.process.current_process()._config.get("tempdir")
    if tempdir:
        shutil.rmtree(tempdir, ignore_errors=True)


def _leave(code: int) -> None:
    """Exit at once with ``code`` once the output is flushed: every file a command writes is
    complete by then (written atomically), the worker pools are shut down, and the interpreter's
    own teardown of the imported libraries would add about a second to every command."""
    logging.shutdown()
    if (event_log := sys.modules.get("forestmap_assets.orchestration.event_log")) is not None:
        event_log.close_all()  # no -wal / -shm files left beside the run history
    _remove_multiprocessing_tempdir()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code if isinstance(code, int) else 1)


if __name__ == "__main__":
    sys.exit(main())
