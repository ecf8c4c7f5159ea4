"""A whole survey, forestmap vs Sylva (issue 16): time, peak memory and pose errors.

For each seed, Sylva's simulator (``sylva.coreg.simulate.simulate_survey``: unorganised clouds of
~1.7 M points, each in its scanner's own levelled frame with an unknown heading) makes a survey,
written here as a forestmap campaign of PLY files (``campaign.yaml`` with one entry per scan and no
prior, ``truth/poses.csv`` in the frame of the first scan). The same clouds are then registered by
Sylva's ``coregister`` and by ``forestmap run CAMPAIGN --no-cloud`` (a new process with a fresh
``FORESTMAP_HOME``, as a user would run it), one after the other. The same is done on campaigns of
forestmap's own simulator at full resolution (``forestmap simulate --resolution full --no-prior
--format ply``), and on scans rendered inside the registered cloud of an own realistic-stem
forest (``sim/cloud_render.py``: a survey-grade "TLS" cloud merged from 9 other positions,
rendered again from the survey's 6, as issue 19's acceptance scans are rendered inside a real
registered cloud). Each child's wall time, CPU time and peak memory are measured
(``getrusage(RUSAGE_CHILDREN)`` of a wrapper process around it, and the process tree's summed PSS
sampled every 0.5 s), and each scan's pose is compared with the truth. Prints the tables and
writes the ``survey`` section of ``benchmarks/results.md``: time and memory with the ratio
forestmap / Sylva, pose errors per scan, forestmap's fine-registration outcome (refined or kept
the branch-and-bound pose, and why) with the pair errors along and across the baseline, and
where each run spends its time (forestmap's stage lines, Sylva's progress lines).

Options: ``--seeds N|a,b`` Sylva surveys (default 3), ``--own-seeds`` own-simulator surveys
(default 1, 0 for none), ``--real-seeds`` own surveys with realistic stems (default 0),
``--render-seeds`` rendered surveys (default 1), ``--colour-render-seeds`` rendered from a colourised
cloud (default 0), ``--ghost-render-seeds`` rendered from a cloud with mixed-pixel ghost points
(default 0), ``--wide-``, ``--dense-``, ``--few-``, ``--noisy-``, ``--splat-``, ``--splat12-render-seeds`` rendered
surveys of other kinds (``RENDER_VARIANTS``, default 0), ``--scans`` (6), ``--skip-peer`` (no
Sylva: own simulator and forestmap only; also what happens, with the error in the section, when
Sylva cannot be installed or imported), ``--cache DIR`` (keep campaigns, logs and stores; simulated campaigns are reused),
``--report-only`` (rebuild the tables from ``--cache``), ``--no-write``.

Sylva (PyPI ``sylva-rs``) is GPL-3: it is only run, as a separate program in its own venv
(``benchmarks/.venv-peer``, from ``benchmarks/requirements-peer.txt``); this file runs itself
there (``--peer ...``) and exchanges PLY files and JSON with it. Nothing of it enters the package.

    python benchmarks/bench_survey.py --seeds 3 --cache /tmp/bench-survey
    python benchmarks/bench_survey.py --skip-peer --own-seeds 2
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import re
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
PEER_VENV = HERE / ".venv-peer"
PEER_REQUIREMENTS = HERE / "requirements-peer.txt"
SECTION = "survey"
GIB = 1024.0**3


# rendered surveys of other kinds (sim/cloud_render.render_campaign options): each has its own
# --<name>-render-seeds flag; results.md "widening_range" measured one seed of each
RENDER_VARIANTS = {
    "renderwide": ("120 trees on a 70 m plot", {"plot_size": 70.0, "trees": 120}),
    "renderdense": ("120 trees on the 40 m plot", {"trees": 120}),
    "renderfew": ("a cloud from 4 source scans", {"source_scans": 4}),
    "rendernoisy": ("1 cm range noise and 12 mm splats", {"range_sigma_m": 0.01, "splat_m": 0.012}),
    "rendersplat": ("15 mm splats", {"splat_m": 0.015}),
    "rendersplat12": ("12 mm splats", {"splat_m": 0.012}),
}

# ----------------------------------------------------------------------------- child processes


def measure_main(out: str, cmd: list[str]) -> int:
    """``--measure OUT -- CMD...``: run CMD and write its wall time, CPU time and peak RSS (the
    largest of CMD and the descendants it waited for) as JSON."""
    t0 = time.perf_counter()
    try:
        rc = subprocess.call(cmd)
    except OSError as e:  # not found, not executable
        print(f"cannot start {cmd[0]}: {e}", flush=True)
        rc = 127
    wall = time.perf_counter() - t0
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    Path(out).write_text(json.dumps({"rc": rc, "wall_s": wall, "user_s": ru.ru_utime,
                                     "sys_s": ru.ru_stime, "maxrss_kib": ru.ru_maxrss}))
    return rc


def run_measured(cmd: list[str], log: Path, env: dict | None = None, echo: bool = True) -> dict:
    """Run ``cmd`` under the measuring wrapper; its output goes to ``log``, each line stamped with
    the seconds since the start. Returns the measurement plus ``lines`` [(t, text)]."""
    usage_file = log.with_suffix(".rusage.json")
    usage_file.unlink(missing_ok=True)
    full = [sys.executable, str(Path(__file__).resolve()), "--measure", str(usage_file), "--",
            *map(str, cmd)]
    env = dict(os.environ if env is None else env, PYTHONUNBUFFERED="1")
    load0 = os.getloadavg()[0]
    lines: list[tuple[float, str]] = []
    rss: list[tuple[float, int]] = []
    cpu: dict[int, tuple[float, float]] = {}
    who: dict[int, tuple[int, str]] = {}
    t0 = time.perf_counter()
    with open(log, "w") as fh, subprocess.Popen(full, stdout=subprocess.PIPE,
                                                stderr=subprocess.STDOUT, text=True, env=env) as p:
        sampler = threading.Thread(target=sample_rss, args=(p, t0, rss, 0.5, cpu, who), daemon=True)
        sampler.start()
        fh.write("# " + " ".join(map(str, cmd)) + "\n")
        for raw in p.stdout:
            t, line = time.perf_counter() - t0, raw.rstrip("\n")
            lines.append((t, line))
            fh.write(f"{t:8.2f} {line}\n")
            fh.flush()
            if echo:
                print(f"      {t:7.1f} {line}", flush=True)
    usage = json.loads(usage_file.read_text()) if usage_file.exists() else {
        "rc": p.returncode, "wall_s": time.perf_counter() - t0, "user_s": math.nan,
        "sys_s": math.nan, "maxrss_kib": math.nan}
    sampler.join(timeout=5)
    # worker processes of a fork server are not the wrapper's waited-for descendants: their CPU
    # time as last sampled (under by at most one sampling interval each)
    sampled = [sum(v) for v in zip(*cpu.values(), strict=True)] if cpu else [0.0, 0.0]
    if sampled[0] + sampled[1] > usage.get("user_s", 0.0) + usage.get("sys_s", 0.0):
        usage["user_s"], usage["sys_s"] = sampled
    usage.update(load_before=load0, load_after=os.getloadavg()[0], lines=lines, rss=rss,
                 procs={pid: {"cpu_s": sum(c), "ppid": who.get(pid, (0, ""))[0],
                              "cmd": who.get(pid, (0, ""))[1]} for pid, c in cpu.items()})
    with open(log.with_suffix(".rss.csv"), "w") as fh:
        fh.write("t_s,rss_bytes\n" + "".join(f"{t:.2f},{b}\n" for t, b in rss))
    return usage


PSS_RISE = 1.02  # a new high of the tree's summed RSS by this factor triggers a PSS reading
PSS_EVERY_S = 10.0  # and at least this often


def sample_rss(proc: subprocess.Popen, t0: float, out: list, every_s: float = 0.5,
               cpu: dict | None = None, who: dict | None = None) -> None:
    """Memory of the whole process tree under ``proc`` every ``every_s`` seconds: the sum of
    each process's proportional set size (PSS: shared pages split, so forked workers are not
    counted twice; RSS where PSS is unreadable); ``cpu``: each process's last seen (user,
    system) seconds; ``who``: each process's parent and command line. psutil; nothing without it.

    PSS makes the kernel walk every page table of a process, 17 ms for a 2.7 GB worker: read
    every half second from four or five processes, it took 2.6 s of CPU (8 % of a core) during a
    31 s forestmap run, and it holds each process's memory map while it walks, so the tool using
    more memory paid more for being measured (session 45). The tree's summed RSS (``statm``, no
    walk) is read at every sample instead, and PSS only when that sum reaches a new high
    (``PSS_RISE``) or ``PSS_EVERY_S`` after the last reading; between readings the PSS is the
    RSS sum times the last reading's PSS / RSS ratio. The peak is a reading's: it comes with the
    RSS sum's peak."""
    try:
        import psutil
    except ImportError:
        return
    try:
        root = psutil.Process(proc.pid)
    except psutil.Error:
        return
    high, ratio, last = 0, 1.0, -math.inf
    while proc.poll() is None:
        try:
            procs = [root, *root.children(recursive=True)]
        except psutil.Error:
            break
        rss = {}
        for q in procs:
            try:
                if cpu is not None:
                    t = q.cpu_times()
                    cpu[q.pid] = (t.user, t.system)
                if who is not None and q.pid not in who:
                    who[q.pid] = (q.ppid(), " ".join(q.cmdline())[:200])
                rss[q] = q.memory_info().rss
            except psutil.Error:
                pass
        now, rss_sum = time.perf_counter() - t0, sum(rss.values())
        if rss_sum > PSS_RISE * high or now - last >= PSS_EVERY_S:
            total = 0
            for q, r in rss.items():
                try:
                    total += q.memory_full_info().pss
                except (psutil.Error, AttributeError):
                    total += r
            high, ratio, last = max(high, rss_sum), total / max(rss_sum, 1), now
        else:
            total = int(rss_sum * ratio)
        out.append((now, total))
        time.sleep(every_s)


def peak_gib(m: dict) -> float:
    """Peak memory of a measured run (GiB): the larger of the biggest single process's maximum
    resident set (getrusage, exact) and the sampled peak of the tree's summed PSS (counts
    worker processes too)."""
    tree = max((b for _, b in m.get("rss", [])), default=0) / GIB
    return max(m["maxrss_kib"] * 1024 / GIB, tree)


def code_state() -> str:
    """forestmap's commit, plus a hash of uncommitted changes to forestmap_assets/ (other
    engineers edit the package while benchmarks run: cases may run on different code)."""
    import hashlib

    def git(*a):
        return subprocess.run(["git", "-C", str(REPO), *a], capture_output=True, text=True).stdout

    head = git("rev-parse", "--short", "HEAD").strip() or "?"
    diff = git("diff", "HEAD", "--", "forestmap_assets")
    untracked = git("ls-files", "--others", "--exclude-standard", "--", "forestmap_assets").split()
    h = hashlib.sha1(diff.encode())
    for f in sorted(untracked):
        h.update(f.encode() + (REPO / f).read_bytes())
    n = len(set(git("diff", "HEAD", "--name-only", "--", "forestmap_assets").split()) | set(untracked))
    return head if n == 0 else f"{head}+{h.hexdigest()[:6]} ({n} files uncommitted)"


def last_error(lines: list[tuple[float, str]]) -> str:
    text = [s for _, s in lines if s.strip()]
    for s in reversed(text):
        if s.startswith(("forestmap:", "Error", "error")) or "Error:" in s:
            return s.strip()
    return text[-1].strip() if text else "no output"


# ----------------------------------------------------------------------------- the peer's side
# These two functions run in the peer venv (numpy and sylva only, no forestmap).

def write_ply_xyz(path: Path, xyz) -> None:
    """Binary little-endian PLY with double x, y, z only (no attributes: the simulator's
    ``label`` is ground truth)."""
    import numpy as np

    xyz = np.ascontiguousarray(xyz, dtype="<f8")
    head = (f"ply\nformat binary_little_endian 1.0\ncomment sylva-rs simulate_survey, scanner frame\n"
            f"element vertex {len(xyz)}\nproperty double x\nproperty double y\nproperty double z\n"
            "end_header\n")
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        fh.write(head.encode("ascii"))
        xyz.tofile(fh)
    os.replace(tmp, path)


def peer_simulate(out: Path, seed: int, scans: int, levelled: bool = True) -> None:
    """Simulate a survey with Sylva, write scans/<id>.ply and sylva_truth.json (true
    ``world_from_scan`` transforms) and check that convention on the stems: each scan's stem
    points at 1.3 m, moved by its transform, must surround the true stem axis."""
    from importlib.metadata import version

    import numpy as np
    from sylva.coreg import simulate

    t0 = time.perf_counter()
    survey = simulate.simulate_survey(n_scans=scans, seed=seed, levelled=levelled)
    sim_s = time.perf_counter() - t0
    (out / "scans").mkdir(parents=True, exist_ok=True)
    names = [f"s{k + 1}" for k in range(len(survey.clouds))]
    check, npts = [], []
    for name, cloud, T in zip(names, survey.clouds, survey.true_transforms, strict=True):
        T = np.asarray(T, dtype=float)
        write_ply_xyz(out / "scans" / f"{name}.ply", cloud.xyz)
        npts.append(len(cloud))
        world = cloud.xyz @ T[:3, :3].T + T[:3, 3]
        label = np.asarray(cloud.attrs["label"])
        offsets = []
        for j, tree in enumerate(survey.plot.trees):
            axis = np.asarray(tree.axis_point(1.3), dtype=float).reshape(-1)[:3]
            m = (label == j) & (np.abs(world[:, 2] - axis[2]) < 0.25)
            if m.sum() >= 20:
                offsets.append(float(np.hypot(*(world[m, :2].mean(axis=0) - axis[:2]))))
        check.append(float(np.median(offsets)) if offsets else math.nan)
        print(f"{name}: {len(cloud)} points, stem check {check[-1]:.3f} m", flush=True)
    # the stems' truth (world frame): axis at 1.3 m above the base, base height, DBH there, and
    # from how many scans Sylva counts the stem as visible (its own recall denominator)
    seen = [np.asarray(v) for v in survey.visible]
    seen = [np.flatnonzero(v) if v.dtype == bool else v for v in seen]
    trees = [[*np.asarray(t.axis_point(1.3), dtype=float).reshape(-1)[:2].tolist(), float(t.base_z),
              2.0 * float(t.radius_at(1.3)), int(sum(j in set(v.tolist()) for v in seen))]
             for j, t in enumerate(survey.plot.trees)]
    truth = {
        "sylva_rs": version("sylva-rs"), "seed": seed, "names": names, "n_points": npts,
        "trees_x_y_base_z_dbh_visible": trees,
        "true_transforms": [np.asarray(T, dtype=float).tolist() for T in survey.true_transforms],
        "plot_size_m": float(survey.plot.size), "n_trees": len(survey.plot.trees),
        "simulate_s": sim_s, "stem_check_m": check,
        "note": "true_transforms are world_from_scan; PLY points are in each scanner's frame",
    }
    (out / "sylva_truth.json").write_text(json.dumps(truth, indent=1))


def peer_coregister(out: Path, names: list[str], clouds: list[str]) -> None:
    """Sylva's ``coregister`` with its default settings on the PLY files; the poses
    (``world_from_scan`` of the raw points, world = the first scan) and pair outcomes as JSON."""
    from importlib.metadata import version

    from sylva import coreg

    t0 = time.perf_counter()
    res = coreg.coregister(clouds, names=names)
    wall = time.perf_counter() - t0
    pairs = []
    for p in res.pairs:
        try:
            matches = int(p.n_stem_matches)
        except Exception:  # noqa: BLE001 - no match object on a failed pair
            matches = -1
        pairs.append({"i": int(p.i), "j": int(p.j), "success": bool(p.success),
                      "reason": str(p.reason), "seconds": float(p.seconds),
                      "stem_matches": matches, "used_icp": bool(p.used_icp)})
    report = res.report()
    print(report, flush=True)
    out.write_text(json.dumps({
        "sylva_rs": version("sylva-rs"), "names": names, "reference": int(res.reference),
        "poses": [res.transform_for(i).tolist() for i in range(len(clouds))],
        "registered": [bool(r) for r in res.registered], "seconds": float(res.seconds),
        "api_wall_s": wall, "pairs": pairs,
        "rejected_pairs": [[int(p.i), int(p.j)] for p in res.rejected_pairs()], "report": report,
    }, indent=1))


# ----------------------------------------------------------------------------- campaigns

def setup_peer(python: Path) -> str | None:
    """Create the peer venv and install sylva-rs; None on success, else the error text."""
    if python.exists():
        return None
    venv = python.parent.parent
    print(f"setting up the peer venv {venv} ...", flush=True)
    python3 = shutil.which("python3") or sys.executable
    for cmd in ([python3, "-m", "venv", str(venv)],
                [str(venv / "bin" / "pip"), "install", "-q", "-r", str(PEER_REQUIREMENTS)]):
        r = subprocess.run(cmd, capture_output=True, text=True)
        if r.returncode != 0:
            err = (r.stderr or r.stdout).strip().splitlines()
            return f"`{' '.join(cmd)}` failed: {err[-1] if err else r.returncode}"
    return None


def peer_works(python: Path) -> str | None:
    r = subprocess.run([str(python), "-c", "import sylva.coreg, sylva.coreg.simulate"],
                       capture_output=True, text=True)
    if r.returncode:
        lines = (r.stderr or r.stdout).strip().splitlines()
        return f"`import sylva.coreg` failed in {python}: {lines[-1] if lines else r.returncode}"
    return None


def write_sylva_campaign(root: Path, truth: dict, tilted: bool = False) -> None:
    """campaign.yaml (one entry per scan, no prior, no sensor step: the clouds are not on a
    scan grid) and truth/poses.csv: every scan in the frame of the first (levelled; with
    ``tilted``, Sylva's ``levelled=False`` scans, in the first scan's own tilted frame: x, y, z
    and the heading of the relative transform, what ``poses.csv`` holds)."""
    import numpy as np

    T = [np.asarray(t, dtype=float) for t in truth["true_transforms"]]
    tilt = max(math.degrees(math.acos(min(1.0, t[2, 2]))) for t in T)
    if tilt > 1e-6 and not tilted:
        raise SystemExit(f"Sylva's simulated scans are tilted ({tilt:.3g} deg): expected levelled")
    bad = [c for c in truth["stem_check_m"] if not c < 0.5]
    if bad:
        raise SystemExit(f"truth convention check failed (stem offsets {truth['stem_check_m']})")
    inv0 = np.linalg.inv(T[0])
    rows = ["scan,x,y,z,heading_deg"]
    for name, t in zip(truth["names"], T, strict=True):
        m = inv0 @ t
        h = math.degrees(math.atan2(m[1, 0], m[0, 0])) + 0.0  # no -0.0
        rows.append(f"{name},{m[0, 3]:.6f},{m[1, 3]:.6f},{m[2, 3]:.6f},{h:.6f}")
    (root / "truth").mkdir(exist_ok=True)
    (root / "truth" / "poses.csv").write_text("\n".join(rows) + "\n")
    if truth.get("trees_x_y_base_z_dbh_visible"):  # the stems in the first scan's frame
        rows = ["tree_id,x,y,z,dbh_m,n_visible_scans"]
        for k, (x, y, z, dbh, seen) in enumerate(truth["trees_x_y_base_z_dbh_visible"], start=1):
            p = inv0 @ np.array([x, y, z, 1.0])
            rows.append(f"{k},{p[0]:.6f},{p[1]:.6f},{p[2]:.6f},{dbh:.6f},{seen}")
        (root / "truth" / "trees.csv").write_text("\n".join(rows) + "\n")
    scans = "\n".join(f"  - {{id: {n}, path: scans/{n}.ply}}" for n in truth["names"])
    (root / "campaign.yaml").write_text(
        f"# Sylva (sylva-rs {truth['sylva_rs']}) simulate_survey(n_scans={len(T)}, "
        f"seed={truth['seed']}): unorganised PLY\n# in each scanner's own levelled frame, "
        f"unknown heading and position; truth in truth/poses.csv\nname: {root.name}\n"
        f"environment: forest\nscans:\n{scans}\n")


def make_campaign(kind: str, seed: int, args, cache: Path, peer_py: Path | None) -> dict:
    """The campaign folder of (kind, seed), simulated once per cache; returns its facts."""
    root = cache / f"{kind}-seed{seed}"
    stamp = cache / f"{kind}-seed{seed}.json"
    if stamp.exists() and (root / "campaign.yaml").exists():
        return json.loads(stamp.read_text())
    shutil.rmtree(root, ignore_errors=True)
    root.mkdir(parents=True)
    log = cache / f"{kind}-seed{seed}.simulate.log"
    print(f"  simulating {root} ...", flush=True)
    if kind in ("sylva", "sylvatilt"):
        tilted = ["--tilted"] if kind == "sylvatilt" else []
        m = run_measured([peer_py, Path(__file__).resolve(), "--peer", "simulate", "--seed", seed,
                          "--scans", args.scans, *tilted, "--out", root], log, echo=False)
        if m["rc"]:
            raise SystemExit(f"Sylva's simulator failed: {last_error(m['lines'])} (log {log})")
        truth = json.loads((root / "sylva_truth.json").read_text())
        (root / "truth").mkdir(exist_ok=True)
        os.replace(root / "sylva_truth.json", root / "truth" / "sylva_truth.json")
        write_sylva_campaign(root, truth, tilted=kind == "sylvatilt")
        facts = {"points": truth["n_points"], "stem_check_m": truth["stem_check_m"],
                 "source": f"sylva-rs {truth['sylva_rs']}"}
    elif kind in ("render", "rendercolour", "renderghost", *RENDER_VARIANTS):
        import time as _t

        from forestmap_assets.sim.cloud_render import render_campaign

        t0 = _t.perf_counter()
        variant = RENDER_VARIANTS.get(kind, ("", {}))[1]
        render_campaign(root, seed=seed, scans=args.scans, colour=kind == "rendercolour",
                        source_kwargs={"mixed_range": "blend"} if kind == "renderghost" else None,
                        progress=lambda msg: print(f"    {msg}", flush=True), **variant)
        m = {"wall_s": _t.perf_counter() - t0}
        facts = {"points": [ply_vertices(p) for p in sorted((root / "scans").glob("*.ply"))],
                 "source": "forestmap sim/cloud_render.py (realistic stems, 9 source scans"
                           + {"rendercolour": ", colourised)", "renderghost": ", mixed-pixel ghosts)",
                              **{k: f", {v[0]})" for k, v in RENDER_VARIANTS.items()}}.get(kind, ")")}
    else:
        stems = ["--stems", "realistic"] if kind == "ownreal" else []
        m = run_measured([forestmap_exe(), "simulate", root, "--scans", args.scans, "--resolution",
                          "full", "--no-prior", "--format", "ply", "--seed", seed, *stems], log, echo=False)
        if m["rc"]:
            raise SystemExit(f"forestmap simulate failed: {last_error(m['lines'])} (log {log})")
        facts = {"points": [ply_vertices(p) for p in sorted((root / "scans").glob("*.ply"))],
                 "source": "forestmap simulate --resolution full " + " ".join(stems)}
    facts.update(kind=kind, seed=seed, root=str(root), simulate_wall_s=m["wall_s"],
                 scans=scan_list(root))
    stamp.write_text(json.dumps(facts))
    return facts


def ply_vertices(path: Path) -> int:
    with open(path, "rb") as fh:
        for raw in fh:
            if raw.startswith(b"element vertex"):
                return int(raw.split()[2])
            if raw.startswith(b"end_header"):
                break
    return 0


def scan_list(root: Path) -> list[dict]:
    """[{id, path}] of campaign.yaml, in order (the first scan is the reference)."""
    import yaml

    doc = yaml.safe_load((root / "campaign.yaml").read_text())
    return [{"id": str(s["id"]), "path": str(root / s["path"])} for s in doc["scans"]]


def forestmap_exe() -> Path:
    exe = Path(sys.executable).with_name("forestmap")
    return exe if exe.exists() else REPO / ".venv" / "bin" / "forestmap"


# ----------------------------------------------------------------------------- the two runs

STEP = re.compile(r"^  (?:\[(?P<scan>[^\]]+)\] )?(?P<stage>[a-z_]+) \((?P<s>\d+(?:\.\d+)?) s\)$")
# one pair partition's search (issue 17): "  [S__T] pairwise_registrations (2.9 s)"
PAIR = re.compile(r"^  \[(?P<pair>\S+__\S+)\] pairwise_registrations \((?P<s>\d+(?:\.\d+)?) s\)$")


def stage_breakdown(lines: list[tuple[float, str]],
                    rss: list[tuple[float, int]] = ()) -> dict[str, list[float]]:
    """{stage: [seconds, peak GiB]} from forestmap's log: seconds summed over the scans, peak
    resident memory of the tree sampled while the stage ran (NaN without samples); plus the
    start-up (until its first line) and the exports (after the last stage). Steps of two workers
    overlap, so the rows do not add up to the wall (:func:`cpu_by_process` says where the CPU
    goes)."""
    windows: dict[str, list[tuple[float, float]]] = {}
    secs: dict[str, float] = {}
    last_step, first = None, lines[0][0] if lines else 0.0
    written = None
    for t, s in lines:
        m = STEP.match(s.rstrip())
        if m:
            secs[m["stage"]] = secs.get(m["stage"], 0.0) + float(m["s"])
            windows.setdefault(m["stage"], []).append((t - float(m["s"]), t))
            last_step = t
        elif s.startswith("outputs written"):
            written = t
    res = {"start-up (imports, definitions)": [first, *_peak(rss, [(0.0, first)])]}
    res.update({k: [v, *_peak(rss, windows[k])] for k, v in secs.items()})
    if last_step is not None and written is not None:
        res["exports (no cloud)"] = [written - last_step, *_peak(rss, [(last_step, written)])]
    return res


def first_step_start(lines: list[tuple[float, str]]) -> float | None:
    """Seconds from the launch to the start of the first step (its log line's time less the
    Dagster step duration it prints, to about 0.1 s): until then no step body has run on any
    core, so the run's wall time is at least this plus the step bodies' CPU over the cores."""
    starts = [t - float(m["s"]) for t, s in lines if (m := STEP.match(s.rstrip()))]
    return min(starts) if starts else None


def _peak(rss, windows) -> list[float]:
    v = [b for t, b in rss for a, z in windows if a - 0.6 <= t <= z + 0.3]
    return [max(v) / GIB if v else math.nan]


SYLVA_PHASES = (("Preparing", "start-up (imports)"), ("Screening", "prepare scans (read, ground, stems)"),
                ("Refining", "screen pairs by stem matching"), ("Optimising", "pairs: match + ICP"),
                ("Coregistration of", "pose graph"))


def sylva_phases(lines: list[tuple[float, str]], wall: float) -> dict[str, float]:
    """Seconds per phase of Sylva's run from the times its progress lines appeared."""
    marks = []
    for key, name in SYLVA_PHASES:
        t = next((t for t, s in lines if s.lstrip().startswith(key)), None)
        if t is not None:
            marks.append((t, name))
    res, prev = {}, 0.0
    for t, name in marks:
        res[name] = t - prev
        prev = t
    res["report, exit"] = max(0.0, wall - prev)
    return res


def run_sylva(case: dict, rundir: Path, peer_py: Path) -> dict:
    scans = case["scans"]
    out = rundir / "sylva_result.json"
    out.unlink(missing_ok=True)
    print(f"  Sylva coregister on {len(scans)} scans ...", flush=True)
    m = run_measured([peer_py, Path(__file__).resolve(), "--peer", "coregister", "--out", out,
                      "--names", ",".join(s["id"] for s in scans), *[s["path"] for s in scans]],
                     rundir / "sylva.log")
    res = {k: m[k] for k in ("rc", "wall_s", "user_s", "sys_s", "maxrss_kib", "load_before",
                             "load_after")}
    res["peak_gib"] = peak_gib(m)
    if m["rc"] or not out.exists():
        res["error"] = last_error(m["lines"])
        return res
    import numpy as np

    r = json.loads(out.read_text())
    E = [np.asarray(p, dtype=float) for p in r["poses"]]
    inv0 = np.linalg.inv(E[0])
    poses = {}
    for sid, e, ok in zip(r["names"], E, r["registered"], strict=True):
        if ok:
            a = inv0 @ e
            poses[sid] = [a[0, 3], a[1, 3], a[2, 3], math.degrees(math.atan2(a[1, 0], a[0, 0]))]
    pairs = r["pairs"]
    res["phases"] = sylva_phases(m["lines"], m["wall_s"])
    res.update(poses=poses, api_s=r["api_wall_s"], pairs_tried=len(pairs),
               pairs_ok=sum(p["success"] for p in pairs), pairs_rejected=len(r["rejected_pairs"]),
               pair_seconds=[p["seconds"] for p in pairs])
    return res


def run_forestmap(case: dict, rundir: Path) -> dict:
    home, out = rundir / "fm-home", rundir / "fm-out"
    shutil.rmtree(home, ignore_errors=True)
    shutil.rmtree(out, ignore_errors=True)
    env = {k: v for k, v in os.environ.items()
           if k not in ("DAGSTER_HOME", "FORESTMAP_STORE", "FORESTMAP_CAMPAIGNS")}
    env["FORESTMAP_HOME"] = str(home)
    # a fresh run as a user's first: no tilts estimated by an earlier run (levelling.yaml)
    (Path(case["root"]) / "levelling.yaml").unlink(missing_ok=True)
    print(f"  forestmap run {case['root']} --no-cloud ...", flush=True)
    code = code_state()
    m = run_measured([forestmap_exe(), "run", case["root"], "--no-cloud", "--out", out], rundir / "forestmap.log", env)
    res = {k: m[k] for k in ("rc", "wall_s", "user_s", "sys_s", "maxrss_kib", "load_before",
                             "load_after")}
    res["peak_gib"] = peak_gib(m)
    after = code_state()
    res["code"] = code if after == code else f"{code}, changed during the run to {after}"
    res["stages"] = stage_breakdown(m["lines"], m["rss"])
    res["first_step_s"] = first_step_start(m["lines"])
    res["cpu_by_process"] = cpu_by_process(m.get("procs", {}))
    res["step_cpu_s"] = step_cpu(case, home)
    res["pair_seconds"] = [float(p["s"]) for _, s in m["lines"] if (p := PAIR.match(s))]
    if not (out / "poses.csv").exists():
        res["error"] = last_error(m["lines"])
        return res
    if m["rc"]:
        res["warning"] = last_error(m["lines"])
    import pandas as pd

    poses = pd.read_csv(out / "poses.csv")
    placed = poses[poses["registered"].astype(str).str.lower() == "true"]
    res["poses"] = {str(r.scan): [r.x, r.y, r.z, r.heading_deg] for r in placed.itertuples()}
    res["pose_sd"] = {str(r.scan): [r.sd_x, r.sd_y, r.sd_z, r.sd_heading_deg] for r in placed.itertuples()}
    regs = pd.read_csv(out / "registrations.csv", dtype={"scan": str, "reference": str})
    res["registrations"] = regs["status"].value_counts().to_dict()
    res["refinement"] = refinement_outcome(case, home, m["lines"])
    res["trees"] = tree_scores(Path(case["root"]), out)
    return res


def tree_scores(root: Path, out: Path) -> dict | None:
    """forestmap's tree list against the simulator's stems (``truth/trees.csv``, match within
    0.5 m, ``sim.evaluate``): stems visible from >= 2 scans and how many were found, matched
    trees with a DBH, DBH RMSE and bias (cm), and the list's rows matched to no stem (crown
    parts, branches, understorey)."""
    truth = root / "truth" / "trees.csv"
    if not truth.exists() or not (out / "trees.csv").exists():
        return None
    import pandas as pd

    from forestmap_assets.sim.evaluate import match_trees

    trees = pd.read_csv(out / "trees.csv")
    m = match_trees(trees, pd.read_csv(truth), 0.5)
    seen = m[m["n_visible_scans"] >= 2]
    dbh = m[m["est_dbh_m"].notna()]
    err = 100.0 * (dbh["est_dbh_m"] - dbh["dbh_m"]).to_numpy(float)
    return {"stems": len(m), "visible_2": len(seen), "found_2": int(seen["est_x"].notna().sum()),
            "with_dbh": len(dbh), "dbh_rmse_cm": float((err**2).mean() ** 0.5) if err.size else None,
            "dbh_bias_cm": float(err.mean()) if err.size else None,
            "dbh_max_cm": float(abs(err).max()) if err.size else None,
            "rows": len(trees), "rows_unmatched": int(len(trees) - m["est_x"].notna().sum())}


def cpu_by_process(procs: dict) -> dict[str, float]:
    """CPU seconds of a forestmap run by process (as last sampled, so each under by at most one
    sampling interval): ``main`` (the ``forestmap run`` process: start-up, the campaign-level
    stages, the exports), ``fork server`` (imports the workers' libraries once), ``workers``
    (the per-scan and per-pair steps), ``other``."""
    main = [pid for pid, q in procs.items() if " run " in q["cmd"] and "forkserver" not in q["cmd"]
            and "--measure" not in q["cmd"]]
    server = [pid for pid, q in procs.items() if "forkserver" in q["cmd"] and q["ppid"] in main]
    out = {"main": 0.0, "fork server": 0.0, "workers": 0.0, "other": 0.0}
    for pid, q in procs.items():
        role = ("main" if pid in main else "fork server" if pid in server
                else "workers" if q["ppid"] in server else "other")
        out[role] += q["cpu_s"]
    out["workers_n"] = sum(q["ppid"] in server for q in procs.values())
    return out


def step_cpu(case: dict, home: Path) -> float | None:
    """CPU seconds of every step body of a fresh run (their threads' ``cpu_seconds`` metadata,
    every materialisation, both passes of a levelling run; Open3D's own threads are not
    counted), None when the run history cannot be read."""
    try:
        from dagster import AssetKey, DagsterInstance
        from dagster._core.event_api import AssetRecordsFilter

        from forestmap_assets.assets.common import PIPELINE
        from forestmap_assets.io.campaign import load_campaign

        campaign = load_campaign(case["root"])
        instance = DagsterInstance.from_config(str(home / "dagster"))
        total = 0.0
        for stage, _ in PIPELINE:
            records = instance.fetch_materializations(
                AssetRecordsFilter(asset_key=AssetKey([campaign.key, stage])), limit=10_000).records
            for rec in records:
                meta = rec.asset_materialization.metadata or {}
                total += float(meta["cpu_seconds"].value) if "cpu_seconds" in meta else 0.0
        instance.dispose()
        return total
    except Exception as e:  # noqa: BLE001 - the table leaves it out
        print(f"  (step CPU not readable: {e})", flush=True)
        return None


def refinement_outcome(case: dict, home: Path, lines) -> list[dict]:
    """Per accepted pair: method, what fed the map (``refined`` or ``branch_and_bound``) and
    why, from the stored ``refined_registrations`` (the run's log lines if that fails)."""
    try:
        from forestmap_assets.access import load_asset

        ref = load_asset("refined_registrations", campaign=case["root"],
                         store_url=str(home / "store"))["refinements"]
        out = []
        for r in ref.itertuples():
            row = {"pair": f"{r.scan}-{r.reference}", "method": str(r.method), "used": str(r.used),
                   "reason": str(r.reason), "fit_bnb_mm": 1000 * float(r.fit_bnb_m),
                   "fit_refined_mm": 1000 * float(r.fit_refined_m),
                   "bnb": [float(getattr(r, f"bnb_{d}")) for d in ("dx", "dy", "dz", "dheading_deg")],
                   "ref": [float(getattr(r, f"ref_{d}")) for d in ("dx", "dy", "dz", "dheading_deg")]}
            k = re.search(r"(\d+(?:\.\d+)?)-sigma box", row["reason"])
            if k:  # which components sat on the box edge: |refined - bnb| = k sd
                comps = [c for c, d, sd in zip(("x", "y", "z", "heading"), ("dx", "dy", "dz", "dheading_deg"),
                                                ("sd_x", "sd_y", "sd_z", "sd_heading_deg"), strict=True)
                         if abs(getattr(r, f"ref_{d}") - getattr(r, f"bnb_{d}"))
                         >= float(k[1]) * getattr(r, f"bnb_{sd}") * (1 - 1e-6)]
                row["edge"] = ", ".join(comps)
                row["edge_sd"] = ", ".join(
                    f"{c} sd {1000 * getattr(r, 'bnb_' + sd):.1f} mm" if c != "heading" else
                    f"heading sd {getattr(r, 'bnb_' + sd):.3f} deg"
                    for c, sd in zip(comps, [{"x": "sd_x", "y": "sd_y", "z": "sd_z",
                                              "heading": "sd_heading_deg"}[c] for c in comps],
                                     strict=True))
            out.append(row)
        return out
    except Exception as e:  # noqa: BLE001 - fall back on the log
        print(f"  (refined_registrations not readable: {e}; using the log)", flush=True)
        pat = re.compile(r"^  refines \d+/\d+: (\S+) (\S+) (\S+) \([\d.]+ s\) ?(.*)$")
        return [{"pair": m[1], "method": m[2], "used": m[3], "reason": m[4]}
                for _, s in lines if (m := pat.match(s))]


def relative_truth(truth: dict, scan: str, ref: str) -> list[float]:
    """(dx, dy, dz, dheading) of ``scan`` in the levelled frame of ``ref`` (spec 6.1)."""
    s, r = truth[scan], truth[ref]
    h = math.radians(r[3])
    dx, dy = s[0] - r[0], s[1] - r[1]
    return [math.cos(h) * dx + math.sin(h) * dy, -math.sin(h) * dx + math.cos(h) * dy, s[2] - r[2],
            (s[3] - r[3] + 180.0) % 360.0 - 180.0]


def pair_diagnostics(refinement: list[dict], truth_csv: Path) -> list[dict]:
    """Per accepted pair: the branch-and-bound error along and across the baseline (a scale-like
    bias of the features shows as an along error growing with the distance) and whether the
    refined pose, used or not, lay closer to the truth."""
    import pandas as pd

    t = pd.read_csv(truth_csv, dtype={"scan": str}).set_index("scan")
    truth = {k: [float(v) for v in row] for k, row in t[["x", "y", "z", "heading_deg"]].iterrows()}
    out = []
    for r in refinement:
        if "bnb" not in r:
            continue
        scan, ref = r["pair"].split("-", 1)
        tr = relative_truth(truth, scan, ref)
        dist = math.hypot(tr[0], tr[1])
        ux, uy = tr[0] / dist, tr[1] / dist
        eb = [a - b for a, b in zip(r["bnb"], tr, strict=True)]
        er = [a - b for a, b in zip(r["ref"], tr, strict=True)]
        out.append({"pair": r["pair"], "dist_m": dist, "along_cm": 100 * (eb[0] * ux + eb[1] * uy),
                    "across_cm": 100 * (-eb[0] * uy + eb[1] * ux), "z_cm": 100 * eb[2],
                    "xy_bnb_cm": 100 * math.hypot(eb[0], eb[1]),
                    "xy_refined_cm": 100 * math.hypot(er[0], er[1]), "used": r["used"]})
    return out


def pose_errors(truth_csv: Path, poses: dict | None) -> list[dict]:
    """Per scan but the first: true distance from the reference, and xy, z, heading errors
    (None where the scan was not placed)."""
    import pandas as pd

    truth = pd.read_csv(truth_csv, dtype={"scan": str})
    rows = []
    for r in truth.iloc[1:].itertuples():
        row = {"scan": r.scan, "dist_m": math.hypot(r.x, r.y)}
        p = (poses or {}).get(r.scan)
        if p is None:
            row.update(xy=None, z=None, heading=None)
        else:
            dh = (p[3] - r.heading_deg + 180.0) % 360.0 - 180.0
            row.update(xy=math.hypot(p[0] - r.x, p[1] - r.y), z=p[2] - r.z, heading=dh,
                       x=p[0] - r.x, y=p[1] - r.y)
        rows.append(row)
    return rows


# ----------------------------------------------------------------------------- report

def _f(v, fmt="{:.1f}", none="-"):
    return none if v is None or (isinstance(v, float) and math.isnan(v)) else fmt.format(v)


def _ratio(a, b):
    return a / b if a is not None and b and not math.isnan(a) and not math.isnan(b) else None


def case_name(c: dict) -> str:
    label = {"sylva": "Sylva sim", "sylvatilt": "Sylva unlevelled", "render": "rendered",
             "rendercolour": "rendered, colour", "renderghost": "rendered, ghosts",
             **{k: f"rendered, {v[0]}" for k, v in RENDER_VARIANTS.items()},
             "ownreal": "own realistic"}.get(c["kind"], "own sim")
    return f"{label} {c['seed']}"


def summary_errors(rows: list[dict]) -> tuple[int, float | None, float | None, float | None]:
    ok = [r for r in rows if r["xy"] is not None]
    if not ok:
        return 0, None, None, None
    return (len(ok), max(r["xy"] for r in ok), max(abs(r["z"]) for r in ok),
            max(abs(r["heading"]) for r in ok))


def cpu_table(cases: list[dict]) -> list[str]:
    """Markdown lines: forestmap's CPU by process, its step bodies' share, against Sylva's CPU."""
    have = [c for c in cases if (c["forestmap"].get("cpu_by_process") or {}).get("main")]
    if not have:
        return []
    cores = os.cpu_count() or 2
    rows = {"main process": [], "fork server": [], "workers": [], "total (sampled)": [],
            "step bodies (their threads)": [], "the rest": [], "Sylva's CPU": [],
            f"step bodies / {cores} cores / Sylva's wall": [], "first step starts (s)": [],
            f"(first step + step bodies / {cores} cores) / Sylva's wall": []}
    for c in have:
        fm, p = c["forestmap"], c["forestmap"]["cpu_by_process"]
        total = p["main"] + p["fork server"] + p["workers"] + p["other"]
        body = fm.get("step_cpu_s")
        sylva = c.get("sylva") or {}
        rows["main process"].append(f"{p['main']:.1f}")
        rows["fork server"].append(f"{p['fork server']:.1f}")
        rows["workers"].append(f"{p['workers']:.1f} ({p.get('workers_n', 0)})")
        rows["total (sampled)"].append(f"{total:.1f}")
        rows["step bodies (their threads)"].append(_f(body))
        rows["the rest"].append("-" if body is None else f"{total - body:.1f} ({(total - body) / total:.0%})")
        s_cpu = (sylva.get("user_s") or math.nan) + (sylva.get("sys_s") or math.nan)
        rows["Sylva's CPU"].append(_f(None if math.isnan(s_cpu) else s_cpu))
        wall = sylva.get("wall_s")
        rows[f"step bodies / {cores} cores / Sylva's wall"].append(
            "-" if body is None or not wall else f"{body / cores / wall:.2f}")
        first = fm.get("first_step_s")
        rows["first step starts (s)"].append(_f(first))
        rows[f"(first step + step bodies / {cores} cores) / Sylva's wall"].append(
            "-" if body is None or first is None or not wall else f"{(first + body / cores) / wall:.2f}")
    return ["", "**Where forestmap's CPU goes** (CPU seconds by process, as last sampled every "
            "0.5 s; step bodies: the CPU of the steps' own threads, their `cpu_seconds` metadata, "
            "every materialisation; the rest: start-up imports, Dagster's runs and steps, Parquet "
            "writes, exports and report, Open3D's own threads; the wall ratio the step bodies alone "
            "would give on this machine's cores; the first step body's start; and the lower bound "
            "of the wall ratio that start and these step bodies allow, with no other cost at all):", "",
            "| CPU s | " + " | ".join(case_name(c) for c in have) + " |",
            "|---|" + "---|" * len(have),
            *[f"| {k} | " + " | ".join(v) + " |" for k, v in rows.items()]]


def report(cases: list[dict], meta: dict) -> str:
    L = ["## Whole survey: forestmap vs Sylva (`benchmarks/bench_survey.py`, issue 16)", ""]
    L += [meta["intro"], ""]
    L += ["**Time and peak memory** (each run a new process; CPU = user + system of the process "
          "and its children; peak = the larger of the biggest process's maximum resident set and "
          "the sampled (0.5 s) sum of the process tree's PSS; load = 1-min load average before "
          "the run, forestmap / Sylva):", "",
          "| survey | points / scan (M) | Sylva s | forestmap s | ratio fm/Sylva | Sylva CPU s | "
          "forestmap CPU s | ratio fm/Sylva | Sylva peak GiB | forestmap peak GiB | ratio fm/Sylva | load |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    tr, mr, cr = [], [], []
    for c in cases:
        s, f = c.get("sylva") or {}, c["forestmap"]
        pts = sum(c["points"]) / len(c["points"]) / 1e6
        sw, fw = s.get("wall_s"), f.get("wall_s")
        sm = (s.get("peak_gib") or s.get("maxrss_kib", math.nan) * 1024 / GIB) if s else None
        fm = f.get("peak_gib") or f.get("maxrss_kib", math.nan) * 1024 / GIB
        tr.append(_ratio(fw, sw))
        mr.append(_ratio(fm, sm))
        scpu = s["user_s"] + s["sys_s"] if s else None
        fcpu = f["user_s"] + f["sys_s"]
        cr.append(_ratio(fcpu, scpu))
        L.append(f"| {case_name(c)} | {pts:.2f} | {_f(sw)} | {_f(fw)} | {_f(tr[-1], '{:.2f}')} | "
                 f"{_f(scpu)} | {_f(fcpu)} | {_f(cr[-1], '{:.2f}')} | {_f(sm, '{:.2f}')} | "
                 f"{_f(fm, '{:.2f}')} | {_f(mr[-1], '{:.2f}')} | "
                 f"{f['load_before']:.1f} / {_f(s.get('load_before'))} |")
    codes = list(dict.fromkeys(c["forestmap"].get("code", "?") for c in cases))
    L += ["", "forestmap code: " + "; ".join(
        f"{k} ({', '.join(case_name(c) for c in cases if c['forestmap'].get('code', '?') == k)})"
        for k in codes) + ".", ""]
    L += ["**Pose errors** against the truth, every scan but the reference (placed = scans each "
          "tool placed; max over the placed scans; xy and z in cm, heading in degrees):", "",
          "| survey | placed Sylva | placed forestmap | max xy Sylva | max xy forestmap | "
          "max abs z Sylva | max abs z forestmap | max abs heading Sylva | max abs heading forestmap |",
          "|---|---|---|---|---|---|---|---|---|"]
    for c in cases:
        n = len(c["errors_forestmap"])
        a = summary_errors(c["errors_sylva"]) if c.get("errors_sylva") is not None else None
        b = summary_errors(c["errors_forestmap"])
        sa = (f"{a[0]}/{n}", _f(a[1] and a[1] * 100), _f(a[2] and a[2] * 100), _f(a[3], "{:.2f}")) if a else ("-",) * 4
        L.append(f"| {case_name(c)} | {sa[0]} | {b[0]}/{n} | {sa[1]} | {_f(b[1] and b[1] * 100)} | "
                 f"{sa[2]} | {_f(b[2] and b[2] * 100)} | {sa[3]} | {_f(b[3], '{:.2f}')} |")
    scored = [c for c in cases if c["forestmap"].get("trees")]
    if scored:
        L += ["", "**Trees** (forestmap's `trees.csv` against the simulator's stems, matched within "
              "0.5 m; found = stems the simulator counts as visible from >= 2 scans that have a "
              "tree; DBH over every matched tree with one; rows on no stem: the list's rows matched "
              "to no stem, crown parts, branches and understorey; Sylva's `coregister` makes no tree list):",
              "", "| survey | stems | visible from >= 2 scans | found | trees with DBH | "
              "DBH RMSE cm | DBH bias cm | largest DBH error cm | rows / on no stem |",
              "|---|---|---|---|---|---|---|---|---|"]
        for c in scored:
            t = c["forestmap"]["trees"]
            L.append(f"| {case_name(c)} | {t['stems']} | {t['visible_2']} | {t['found_2']} | "
                     f"{t['with_dbh']} | {_f(t['dbh_rmse_cm'], '{:.2f}')} | "
                     f"{_f(t['dbh_bias_cm'], '{:+.2f}')} | {_f(t['dbh_max_cm'])} | "
                     f"{t.get('rows', '-')} / {t.get('rows_unmatched', '-')} |")
    sig = [c for c in cases if c["forestmap"].get("pose_sd")]
    if sig:
        L += ["", "**forestmap's pose sigmas** (`poses.csv` sd against the true error, every placed "
              "scan but the reference: RMS of error / sd per axis, and the share within 2 sd; "
              "issue 19 asks for an RMS of 0.7-1.3 and >= 90 %):", "",
              "| survey | scans | x | y | z | heading | within 2 sd x / y / z / heading |",
              "|---|---|---|---|---|---|---|"]
        for c in sig:
            sd = c["forestmap"]["pose_sd"]
            ratios = [[r[k] / sd[r["scan"]][i] for i, k in enumerate(("x", "y", "z", "heading"))]
                      for r in c["errors_forestmap"] if r.get("x") is not None and r["scan"] in sd
                      and min(sd[r["scan"]]) > 0]
            if not ratios:
                continue
            cols = list(zip(*ratios, strict=True))
            rms = [math.sqrt(sum(v * v for v in col) / len(col)) for col in cols]
            within = [sum(abs(v) <= 2 for v in col) / len(col) for col in cols]
            L.append(f"| {case_name(c)} | {len(ratios)} | " + " | ".join(f"{v:.2f}" for v in rms)
                     + " | " + " / ".join(f"{w:.0%}" for w in within) + " |")
    L += ["", "Per scan (x = not placed):", "",
          "| survey | scan | distance from reference m | xy cm Sylva | xy cm forestmap | z cm Sylva | "
          "z cm forestmap | heading deg Sylva | heading deg forestmap |",
          "|---|---|---|---|---|---|---|---|---|"]
    for c in cases:
        es = {r["scan"]: r for r in (c.get("errors_sylva") or [])}
        for r in c["errors_forestmap"]:
            s = es.get(r["scan"])
            def cm(v):
                return "x" if v is None else f"{v * 100:.1f}"
            def dg(v):
                return "x" if v is None else f"{v:.2f}"
            L.append(f"| {case_name(c)} | {r['scan']} | {r['dist_m']:.1f} | "
                     f"{cm(s['xy']) if s else '-'} | {cm(r['xy'])} | {cm(s['z']) if s else '-'} | "
                     f"{cm(r['z'])} | {dg(s['heading']) if s else '-'} | {dg(r['heading'])} |")
    L += ["", "**forestmap's registrations and fine registration** (`registrations.csv` status; "
          "`refined_registrations`: accepted pairs whose refined pose fed the map vs those that "
          "kept the branch-and-bound pose, with the reason; Sylva: pairs tried / accepted):", "",
          "| survey | forestmap pairs accepted / rejected / failed | refined | kept branch and bound | "
          "median fit mm b&b / refined | median pair s forestmap | Sylva pairs ok / tried | "
          "median pair s Sylva |",
          "|---|---|---|---|---|---|---|---|"]
    reasons: dict[str, list[str]] = {}
    for c in cases:
        f, s = c["forestmap"], c.get("sylva") or {}
        reg = f.get("registrations", {})
        ref = f.get("refinement", [])
        kept = [r for r in ref if r["used"] != "refined"]
        for r in kept:
            key = re.sub(r"\d+\.\d+", "#", r["reason"] or "(none)")
            detail = f" ({r['reason']})" if key != (r["reason"] or "(none)") else ""
            if r.get("edge"):
                key, detail = f"{r['reason']}, in {r['edge']}", f" ({r['edge_sd']})"
            reasons.setdefault(key, []).append(f"{case_name(c)} {r['pair']}{detail}")
        med = lambda v: _f(sorted(v)[len(v) // 2] if v else None)  # noqa: E731
        med2 = lambda v: _f(sorted(x for x in v if x is not None)[len(v) // 2]  # noqa: E731
                            if v and None not in v else None, "{:.1f}")
        L.append(f"| {case_name(c)} | {reg.get('accepted', 0)} / {reg.get('rejected', 0)} / "
                 f"{reg.get('failed', 0)} | {len(ref) - len(kept)} | {len(kept)} | "
                 f"{med2([r.get('fit_bnb_mm') for r in ref])} / {med2([r.get('fit_refined_mm') for r in ref])} | "
                 f"{med(f.get('pair_seconds', []))} | "
                 f"{s.get('pairs_ok', '-')} / {s.get('pairs_tried', '-')} | {med(s.get('pair_seconds', []))} |")
    if reasons:
        L += ["", "Why the branch-and-bound pose was kept:", ""]
        for key, where in sorted(reasons.items(), key=lambda kv: -len(kv[1])):
            L.append(f"- {len(where)} x {key}: " + "; ".join(where))
    diag = [c for c in cases if c.get("pair_errors")]
    if diag:
        L += ["", "forestmap's branch-and-bound pair errors against the truth (pairs that were "
              "refined or kept, median over the pairs; along = along the baseline, positive = "
              "scans too far apart; the refined pose is counted whether it was used or not):", "",
              "| survey | pairs | median along cm | median along / baseline | median abs across cm | "
              "median abs z cm | refined pose closer to truth | median xy cm b&b / refined |",
              "|---|---|---|---|---|---|---|---|"]
        for c in diag:
            p = c["pair_errors"]
            md = statistics.median
            closer = sum(x["xy_refined_cm"] < x["xy_bnb_cm"] for x in p)
            L.append(f"| {case_name(c)} | {len(p)} | {md(x['along_cm'] for x in p):.1f} | "
                     f"{md(x['along_cm'] / x['dist_m'] for x in p):.2f} % | "
                     f"{md(abs(x['across_cm']) for x in p):.1f} | {md(abs(x['z_cm']) for x in p):.1f} | "
                     f"{closer}/{len(p)} | {md(x['xy_bnb_cm'] for x in p):.1f} / "
                     f"{md(x['xy_refined_cm'] for x in p):.1f} |")
    stages: list[str] = []
    for c in cases:  # an older case's "other": the wall minus the summed stages, < 0 when steps overlap
        stages += [k for k in c["forestmap"]["stages"] if k not in stages and not k.startswith("other")]
    L += ["", "**Where forestmap's run spends its time** (seconds summed over the scans, from its "
          "log lines, and in brackets the peak memory in GiB (summed PSS) sampled while the stage ran; "
          "start-up = until its first line, exports = after the last stage; two workers' steps "
          "overlap, so the rows do not add up to the wall):", "",
          "| stage | " + " | ".join(case_name(c) for c in cases) + " | mean share of wall |",
          "|---|" + "---|" * (len(cases) + 1)]
    for st in stages:
        v = [c["forestmap"]["stages"].get(st, [0.0, math.nan]) for c in cases]
        share = sum(x[0] / c["forestmap"]["wall_s"] for x, c in zip(v, cases, strict=True)) / len(cases)
        L.append(f"| {st} | " + " | ".join(f"{x[0]:.1f}" + ("" if math.isnan(x[1]) else f" ({x[1]:.1f})")
                                          for x in v) + f" | {share:.0%} |")
    L.append("| wall | " + " | ".join(f"{c['forestmap']['wall_s']:.1f}" for c in cases) + " | 100% |")
    L += cpu_table(cases)
    sy = [c for c in cases if (c.get("sylva") or {}).get("phases")]
    if sy:
        names = [n for _, n in SYLVA_PHASES] + ["report, exit"]
        L += ["", "Sylva's run by phase (seconds, from the times of its progress lines):", "",
              "| phase | " + " | ".join(case_name(c) for c in sy) + " |", "|---|" + "---|" * len(sy)]
        for n in names:
            L.append(f"| {n} | " + " | ".join(_f(None if (v := c["sylva"]["phases"].get(n)) is None
                                                    else max(0.0, v)) for c in sy) + " |")
        L.append("| wall | " + " | ".join(f"{c['sylva']['wall_s']:.1f}" for c in sy) + " |")
    good_t = [x for x in tr if x is not None]
    good_m = [x for x in mr if x is not None]
    good_c = [x for x in cr if x is not None]
    if good_t:
        L += ["", f"Ratio forestmap / Sylva over the {len(good_t)} surveys: wall time "
              f"{min(good_t):.2f}-{max(good_t):.2f} (median {statistics.median(good_t):.2f}), "
              + f"CPU time {min(good_c):.2f}-{max(good_c):.2f} (median {statistics.median(good_c):.2f}), "
              + (f"peak memory {min(good_m):.2f}-{max(good_m):.2f} (median {statistics.median(good_m):.2f})."
                 if good_m else "")]
        on_sylva = [r for c, r in zip(cases, tr, strict=True) if c["kind"] == "sylva" and r is not None]
        if on_sylva:  # the figure: the median over Sylva's own surveys
            L.append(f"On Sylva's {len(on_sylva)} surveys alone: wall time median "
                     f"{statistics.median(on_sylva):.2f} (issue 16: <= 1.0, goal 0.25).")
    if meta.get("notes"):
        L += [""] + meta["notes"]
    return "\n".join(L)


# ----------------------------------------------------------------------------- main

def backfill(case: dict, rundir: Path) -> dict:
    """--report-only: derive what an older case.json lacks from the run's files, if kept."""
    f, home = case["forestmap"], rundir / "fm-home"
    if any("bnb" not in r for r in f.get("refinement", [])) and home.exists():
        f["refinement"] = refinement_outcome(case, home, [])
    truth = Path(case["root"]) / "truth" / "poses.csv"
    out = rundir / "fm-out" / "poses.csv"
    if "pose_sd" not in f and out.exists() and truth.exists():
        import pandas as pd

        poses = pd.read_csv(out, dtype={"scan": str})
        placed = poses[poses["registered"].astype(str).str.lower() == "true"]
        f["pose_sd"] = {r.scan: [r.sd_x, r.sd_y, r.sd_z, r.sd_heading_deg] for r in placed.itertuples()}
        case["errors_forestmap"] = pose_errors(truth, f.get("poses"))
    if "pair_errors" not in case and truth.exists():
        case["pair_errors"] = pair_diagnostics(f.get("refinement", []), truth)
    if "trees" not in f:
        f["trees"] = tree_scores(Path(case["root"]), rundir / "fm-out")
    log = rundir / "sylva.log"
    if case.get("sylva") and "phases" not in case["sylva"] and log.exists():
        lines = []
        for ln in log.read_text().splitlines()[1:]:
            t, _, text = ln.strip().partition(" ")
            lines.append((float(t), text))
        case["sylva"]["phases"] = sylva_phases(lines, case["sylva"]["wall_s"])
    return case


def seeds_of(text: str) -> list[int]:
    """``N``: seeds 1..N; a list ``4,7`` (one seed: ``17,``) or a range ``11-16``."""
    if "-" in text:
        lo, hi = (int(v) for v in text.split("-", 1))
        return list(range(lo, hi + 1))
    return [int(s) for s in text.split(",") if s] if "," in text else list(range(1, int(text) + 1))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="3", help="Sylva surveys: N (seeds 1..N), a list 4,7 (one seed: 17,) or a range 11-16 (default 3)")
    ap.add_argument("--own-seeds", default="1", help="surveys of forestmap's own simulator, same form (0: none)")
    ap.add_argument("--real-seeds", default="0",
                    help="own-simulator surveys with realistic stems (--stems realistic), same form (0: none)")
    ap.add_argument("--colour-render-seeds", default="0",
                    help="as --render-seeds, the cloud colourised and the scans with its RGB (0: none)")
    ap.add_argument("--ghost-render-seeds", default="0",
                    help="as --render-seeds, the source scanner's mixed pixels echo both surfaces "
                         "(ghost points trailing the trunks' silhouettes, as real TLS clouds have; 0: none)")
    for kind, (what, _) in RENDER_VARIANTS.items():
        ap.add_argument(f"--{kind[6:]}-render-seeds", default="0", help=f"as --render-seeds, {what} (0: none)")
    ap.add_argument("--render-seeds", default="1",
                    help="surveys rendered inside the registered cloud of an own realistic forest "
                         "(sim/cloud_render.py), same form (0: none)")
    ap.add_argument("--tilted-seeds", default="0",
                    help="Sylva surveys of unlevelled scans (simulate_survey(levelled=False): "
                         "roll and pitch up to 0.5 deg, not given to forestmap), same form")
    ap.add_argument("--scans", type=int, default=6)
    ap.add_argument("--skip-peer", action="store_true", help="no Sylva: own simulator and forestmap only")
    ap.add_argument("--cache", type=Path, help="keep the simulated campaigns and runs here (reused)")
    ap.add_argument("--peer-python", type=Path, default=PEER_VENV / "bin" / "python")
    ap.add_argument("--no-write", action="store_true", help="print only, leave results.md alone")
    ap.add_argument("--report-only", action="store_true", help="rebuild the tables from --cache's runs")
    args = ap.parse_args(argv)

    cache = args.cache or Path(tempfile.mkdtemp(prefix="bench-survey-"))
    cache.mkdir(parents=True, exist_ok=True)
    notes, peer_py = [], None
    if not args.skip_peer:
        err = setup_peer(args.peer_python) or peer_works(args.peer_python)
        if err:
            print(f"Sylva cannot run here: {err}", flush=True)
            notes.append(f"Sylva could not run here, so only forestmap was measured: {err}")
        else:
            peer_py = args.peer_python
    plan = [("sylva", s) for s in (seeds_of(args.seeds) if peer_py else [])]
    plan += [("sylvatilt", s) for s in (seeds_of(args.tilted_seeds) if peer_py and args.tilted_seeds != "0" else [])]
    plan += [("own", s) for s in (seeds_of(args.own_seeds) if args.own_seeds != "0" else [])]
    plan += [("ownreal", s) for s in (seeds_of(args.real_seeds) if args.real_seeds != "0" else [])]
    plan += [("render", s) for s in (seeds_of(args.render_seeds) if args.render_seeds != "0" else [])]
    plan += [("rendercolour", s) for s in (seeds_of(args.colour_render_seeds) if args.colour_render_seeds != "0" else [])]
    plan += [("renderghost", s) for s in (seeds_of(args.ghost_render_seeds) if args.ghost_render_seeds != "0" else [])]
    for kind in RENDER_VARIANTS:
        seeds = getattr(args, f"{kind[6:]}_render_seeds")
        plan += [(kind, s) for s in (seeds_of(seeds) if seeds != "0" else [])]
    cases = []
    for kind, seed in plan:
        rundir = cache / "runs" / f"{kind}-seed{seed}"
        done = rundir / "case.json"
        if args.report_only:
            if done.exists():
                cases.append(backfill(json.loads(done.read_text()), rundir))
            continue
        print(f"{kind} seed {seed}:", flush=True)
        case = make_campaign(kind, seed, args, cache, peer_py)
        rundir.mkdir(parents=True, exist_ok=True)
        truth = Path(case["root"]) / "truth" / "poses.csv"
        if peer_py:
            case["sylva"] = run_sylva(case, rundir, peer_py)
            case["errors_sylva"] = pose_errors(truth, case["sylva"].get("poses"))
        case["forestmap"] = run_forestmap(case, rundir)
        case["errors_forestmap"] = pose_errors(truth, case["forestmap"].get("poses"))
        case["pair_errors"] = pair_diagnostics(case["forestmap"].get("refinement", []), truth)
        for who in ("sylva", "forestmap"):
            if (case.get(who) or {}).get("error"):
                notes.append(f"{case_name(case)}: {who} failed: {case[who]['error']}")
        done.write_text(json.dumps(case, indent=1, default=float))
        cases.append(case)
        if not args.cache:
            shutil.rmtree(case["root"], ignore_errors=True)
    if not cases:
        print("nothing measured", file=sys.stderr)
        return 1
    try:
        commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"],
                                capture_output=True, text=True).stdout.strip()
    except OSError:
        commit = "?"
    cpu = platform.processor() or platform.machine()
    try:
        cpu = next(ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name"))
    except (OSError, StopIteration):
        pass
    sylva_v = next((c["source"] for c in cases if c["kind"] in ("sylva", "sylvatilt")), "not run")
    intro = (f"{time.strftime('%Y-%m-%d')}, forestmap {commit}, Sylva: {sylva_v}, {os.cpu_count()} cores "
             f"({cpu}) shared with other work, {args.scans} scans per survey, no prior. Sylva surveys: "
             "`sylva.coreg.simulate.simulate_survey(n_scans, seed)` (40 m plot, 45 trees, scans within "
             "12 m of the centre, levelled, unknown heading), each cloud written as a PLY of x, y, z "
             "in its scanner's frame, `campaign.yaml` without prior or sensor step; own surveys: "
             "`forestmap simulate OUT --scans 6 --resolution full --no-prior --format ply --seed S` "
             "(own realistic: with `--stems realistic`). "
             "On each survey, Sylva's `coregister(ply_files, names=...)` (default `CoregConfig`) and "
             "`forestmap run CAMPAIGN --no-cloud` (fresh `FORESTMAP_HOME`, default in-process "
             "executor; it also builds the tree list, elevation model, next vantage points, "
             "map.png and report.html) read the same PLY files.")
    body = report(cases, {"intro": intro, "notes": notes})
    print("\n" + body)
    if not args.no_write:
        from results_md import write_section

        write_section(SECTION, body)
        print(f"\nwrote section '{SECTION}' of {HERE / 'results.md'}")
    if not args.cache:
        shutil.rmtree(cache, ignore_errors=True)
    return 0


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[1] == "--measure":
        sep = sys.argv.index("--")
        sys.exit(measure_main(sys.argv[2], sys.argv[sep + 1:]))
    if len(sys.argv) > 2 and sys.argv[1] == "--peer":
        pp = argparse.ArgumentParser()
        pp.add_argument("--peer", choices=["simulate", "coregister"])
        pp.add_argument("--seed", type=int, default=1)
        pp.add_argument("--scans", type=int, default=6)
        pp.add_argument("--tilted", action="store_true", help="simulate_survey(levelled=False)")
        pp.add_argument("--out", type=Path)
        pp.add_argument("--names", default="")
        pp.add_argument("clouds", nargs="*")
        a = pp.parse_args()
        if a.peer == "simulate":
            peer_simulate(a.out, a.seed, a.scans, levelled=not a.tilted)
        else:
            peer_coregister(a.out, a.names.split(","), a.clouds)
        sys.exit(0)
    sys.exit(main())
