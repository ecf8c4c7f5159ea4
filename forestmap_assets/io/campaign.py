"""The campaign folder and its ``campaign.yaml`` (DESIGN.md section 2).

:func:`load_campaign` reads and validates the manifest. Every problem is reported as one
:class:`CampaignError` line naming the file and the field, e.g.
``plot/campaign.yaml: scans[1].id: duplicate scan id 'T'``.
"""

from __future__ import annotations

import hashlib
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from forestmap_assets.io.home import campaign_key, file_digest
from forestmap_assets.io.levelling_file import read_levelling
from forestmap_assets.io.scan_poses import PoseError, e57_poses, parse_pose
from forestmap_assets.params import Params, ParamsError, resolve_params

MANIFEST = "campaign.yaml"
SCAN_ID = re.compile(r"^[A-Za-z0-9_-]+$")
SCAN_EXTENSIONS = (".npz", ".e57", ".las", ".laz", ".ply", ".pcd", ".xyz", ".txt", ".csv")

_TOP_KEYS = {"name", "environment", "scans", "pairs", "search", "params", "sensor",
             "a_priori_from_file"}
_SCAN_KEYS = {"id", "path", "tilt_deg", "a_priori", "pose", "e57_scan", "a_priori_from_file"}
_POSE_KEYS = {"x", "y", "z", "roll_deg", "pitch_deg", "heading_deg"}
POINT_CLOUD_EXTENSIONS = (".las", ".laz", ".ply", ".pcd", ".xyz", ".txt", ".csv")
_PAIR_KEYS = {"scan", "reference", "a_priori", "search"}
_SEARCH_KEYS = {"xy_m", "z_m", "heading_deg"}
_SENSOR_KEYS = {"angular_step_deg", "beam_divergence_mrad", "beam_exit_mm"}


class CampaignError(ValueError):
    """An invalid campaign folder or manifest; the message is one line naming file and field."""


@dataclass(frozen=True)
class ScanEntry:
    """One scan position of the campaign."""

    id: str
    path: Path
    tilt_deg: tuple[float, float] = (0.0, 0.0)
    a_priori: tuple[float, float, float, float] | None = None
    e57_scan: int | None = None  # data3D index in a multi-scan E57
    pose: tuple[tuple[float, ...], ...] | None = None  # 4x4 scanner -> file frame (``pose:``)
    prior_source: str | None = None  # where ``a_priori`` came from: campaign.yaml, pose, e57 pose
    levelled_from: tuple[float, float] | None = None  # the entry's own tilt, when levelling.yaml's replaced it
    tilt_sd_deg: float = 0.0  # the sd of that estimate (0: a measured tilt)

    @property
    def to_scanner(self):
        """The 4x4 file-to-scanner transform that moves a project-frame file's points to the
        scanner's own frame before projection (None: the file is in the scanner frame)."""
        if self.pose is None:
            return None
        import numpy as np

        m = np.asarray(self.pose, dtype=np.float64)
        inv = np.eye(4)
        inv[:3, :3] = m[:3, :3].T
        inv[:3, 3] = -m[:3, :3].T @ m[:3, 3]
        return inv


@dataclass(frozen=True)
class PairEntry:
    """An a priori alignment of ``scan`` in the levelled frame of ``reference``."""

    scan: str
    reference: str
    a_priori: tuple[float, float, float, float]
    search: tuple[tuple[str, float], ...] | None = None  # per-pair box (core/pair_checks.py)


@dataclass(frozen=True)
class Campaign:
    """A validated campaign: its folder, scans, optional pairs and resolved parameters."""

    root: Path
    name: str
    environment: str
    scans: tuple[ScanEntry, ...]
    pairs: tuple[PairEntry, ...] = ()
    search: dict[str, float] | None = None
    angular_step_deg: float | tuple[float, float] | None = None
    params: Params = field(default_factory=Params)

    @property
    def key(self) -> str:
        """Name usable as a Dagster asset-key prefix and storage folder: ``[A-Za-z0-9_]+``."""
        return campaign_key(self.name)

    @property
    def prior_note(self) -> str:
        """Where the a priori scan poses come from when the files gave them ('' otherwise)."""
        counts: dict[str, int] = {}
        for s in self.scans:
            if s.prior_source in ("e57 pose", "pose"):
                counts[s.prior_source] = counts.get(s.prior_source, 0) + 1
        said = {"e57 pose": "the E57 file's scan poses", "pose": "the scans' pose: entries"}
        parts = [f"{said[k]} ({n} scans)" for k, n in counts.items()]
        return f"; a priori poses from {' and '.join(parts)}" if parts else ""

    @property
    def scan_ids(self) -> list[str]:
        return [s.id for s in self.scans]

    def scan(self, scan_id: str) -> ScanEntry:
        for s in self.scans:
            if s.id == scan_id:
                return s
        raise KeyError(scan_id)

    def scan_fingerprint(self, scan_id: str) -> str:
        """Content hash of a scan file plus its tilt (a Dagster data version for the input)."""
        entry = self.scan(scan_id)
        h = hashlib.sha256(file_digest(entry.path).encode())
        key: tuple = (entry.tilt_deg, self.angular_step_deg)
        if entry.pose is not None or entry.e57_scan is not None:
            key += (entry.pose, entry.e57_scan)
        h.update(repr(key).encode())
        return h.hexdigest()[:20]


def _fail(where: str, message: str) -> CampaignError:
    return CampaignError(f"{where}: {message}")


def _numbers(value: Any, n: int, where: str, field_name: str) -> tuple[float, ...]:
    ok = isinstance(value, (list, tuple)) and len(value) == n
    if ok:
        try:
            out = tuple(float(v) for v in value)
        except (TypeError, ValueError):
            ok = False
        else:
            if all(math.isfinite(v) and not isinstance(v0, bool) for v, v0 in zip(out, value, strict=True)):
                return out
            ok = False
    raise _fail(where, f"{field_name}: expected a list of {n} numbers, got {value!r}")


def _positive(value: Any, where: str, field_name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
        raise _fail(where, f"{field_name}: expected a positive number, got {value!r}")
    return float(value)


def _non_negative(value: Any, where: str, field_name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value >= 0:
        raise _fail(where, f"{field_name}: expected a number >= 0, got {value!r}")
    return float(value)


def _unknown(keys: Any, allowed: set[str], where: str, prefix: str) -> None:
    extra = sorted(set(keys) - allowed)
    if extra:
        raise _fail(where, f"{prefix}{extra[0]}: unknown key (allowed: {', '.join(sorted(allowed))})")


def _scan_entry(raw: dict, sid: str, path: Path, where: str, at: str, from_file: bool,
                e57_cache: dict) -> ScanEntry:
    """The tilt, a priori pose, E57 index and project-frame pose of one scan entry: what
    ``campaign.yaml`` says first, then what the file's pose says (E57, or the entry's ``pose``)."""
    ext = path.suffix.lower()
    tilt_raw, prior_raw = raw.get("tilt_deg"), raw.get("a_priori")
    tilt = _numbers(tilt_raw, 2, where, f"{at}.tilt_deg") if tilt_raw is not None else None
    prior = _numbers(prior_raw, 4, where, f"{at}.a_priori") if prior_raw is not None else None
    source = "campaign.yaml" if prior is not None else None
    use_file = raw.get("a_priori_from_file", from_file)
    if not isinstance(use_file, bool):
        raise _fail(where, f"{at}.a_priori_from_file: expected true or false, got {use_file!r}")
    e57_scan, matrix, file_pose = raw.get("e57_scan"), None, None
    if e57_scan is not None:
        if ext != ".e57":
            raise _fail(where, f"{at}.e57_scan: only for .e57 files, not {ext}")
        if isinstance(e57_scan, bool) or not isinstance(e57_scan, int) or e57_scan < 0:
            raise _fail(where, f"{at}.e57_scan: expected a scan index 0, 1, 2, ..., got {e57_scan!r}")
    if ext == ".e57":
        if path not in e57_cache:
            e57_cache[path] = e57_poses(path)
        listed = e57_cache[path]
        if listed is not None:
            if e57_scan is None and len(listed) > 1:
                raise _fail(where, f"{at}.e57_scan: {path.name} holds {len(listed)} scans; give "
                            f"e57_scan: 0..{len(listed) - 1} (forestmap init writes one entry each)")
            if e57_scan is not None and e57_scan >= len(listed):
                raise _fail(where, f"{at}.e57_scan: {e57_scan} out of range ({path.name} holds "
                            f"{len(listed)} scans)")
            file_pose = listed[e57_scan or 0][1]
    if "pose" in raw:
        if ext not in POINT_CLOUD_EXTENSIONS:
            raise _fail(where, f"{at}.pose: only for point-cloud files ({' '.join(POINT_CLOUD_EXTENSIONS)}); "
                        f"{ext} scans are in the scanner's frame")
        try:
            file_pose = parse_pose(raw["pose"])
        except PoseError as exc:
            field_name = f"{at}.pose.{exc.key}" if exc.key else f"{at}.pose"
            raise _fail(where, f"{field_name}: {exc}") from None
        matrix = tuple(tuple(float(v) for v in row) for row in file_pose.matrix)
        use_file = True  # the campaign's own pose: its position is the a priori pose
    if file_pose is not None:
        if tilt is None:
            tilt = file_pose.tilt_deg
        if prior is None and use_file:
            prior = file_pose.a_priori
            source = "pose" if matrix is not None else "e57 pose"
    tilt = tilt if tilt is not None else (0.0, 0.0)
    return ScanEntry(sid, path, (tilt[0], tilt[1]), prior, e57_scan, matrix, source)  # type: ignore[arg-type]


def _drop_placeholder_poses(scans: list[ScanEntry]) -> list[ScanEntry]:
    """An E57 whose scans all stand at one position was not registered by its software (identity
    or tilt-only poses): keep the tilt, drop the positions as a priori poses."""
    from dataclasses import replace

    by_file: dict[Path, list[ScanEntry]] = {}
    for s in scans:
        if s.prior_source == "e57 pose":
            by_file.setdefault(s.path, []).append(s)
    drop = set()
    for group in by_file.values():
        xyz = [s.a_priori[:3] for s in group if s.a_priori is not None]
        if len(group) > 1 and max(math.dist(xyz[0], p) for p in xyz) < 0.01:
            drop.update(s.id for s in group)
    return [replace(s, a_priori=None, prior_source=None) if s.id in drop else s for s in scans]


def _with_levelling(root: Path, scans: list[ScanEntry]) -> list[ScanEntry]:
    """The scans with the tilts of ``levelling.yaml`` (:mod:`.levelling_file`) where their entry
    still gives the tilt the estimate was made from."""
    from dataclasses import replace

    try:
        estimates, _ = read_levelling(root)
    except ValueError as exc:
        raise CampaignError(str(exc)) from None
    out = []
    for s in scans:
        rec = estimates.get(s.id)
        if rec is not None and max(abs(a - b) for a, b in zip(rec["from_tilt_deg"], s.tilt_deg, strict=True)) < 1e-9:
            s = replace(s, tilt_deg=rec["tilt_deg"], levelled_from=s.tilt_deg, tilt_sd_deg=rec["sd_deg"])
        out.append(s)
    return out


def load_campaign(folder: str | Path) -> Campaign:
    """Read and validate ``folder/campaign.yaml``; raise :class:`CampaignError` on any problem."""
    root = Path(folder).expanduser().resolve()
    manifest = root / MANIFEST
    where = str(manifest)
    if not root.is_dir():
        raise CampaignError(f"{root}: campaign folder does not exist")
    if not manifest.is_file():
        raise CampaignError(f"{manifest}: missing campaign manifest")
    try:
        doc = yaml.safe_load(manifest.read_text())
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f" at line {mark.line + 1}" if mark is not None else ""
        raise _fail(where, f"not valid YAML{line}") from None
    if not isinstance(doc, dict):
        raise _fail(where, "expected a mapping at the top level")
    _unknown(doc, _TOP_KEYS, where, "")

    name = doc.get("name", root.name)
    if not isinstance(name, str) or not name.strip():
        raise _fail(where, f"name: expected a non-empty string, got {name!r}")
    environment = doc.get("environment", "forest")
    if environment not in ("forest", "outdoor", "indoor"):
        raise _fail(where, f"environment: expected forest, outdoor or indoor, got {environment!r}")

    raw_scans = doc.get("scans")
    if not isinstance(raw_scans, list) or not raw_scans:
        raise _fail(where, "scans: expected a non-empty list of scans")
    from_file = doc.get("a_priori_from_file", True)
    if not isinstance(from_file, bool):
        raise _fail(where, f"a_priori_from_file: expected true or false, got {from_file!r}")
    e57_cache: dict[Path, list | None] = {}
    scans: list[ScanEntry] = []
    seen: set[str] = set()
    for i, raw in enumerate(raw_scans):
        at = f"scans[{i}]"
        if not isinstance(raw, dict):
            raise _fail(where, f"{at}: expected a mapping with id and path")
        _unknown(raw, _SCAN_KEYS, where, f"{at}.")
        sid = raw.get("id")
        if isinstance(sid, int) and not isinstance(sid, bool):
            sid = str(sid)
        if not isinstance(sid, str) or not SCAN_ID.match(sid):
            raise _fail(where, f"{at}.id: expected letters, digits, '_' or '-', got {sid!r}")
        if sid in seen:
            raise _fail(where, f"{at}.id: duplicate scan id {sid!r}")
        seen.add(sid)
        rel = raw.get("path")
        if not isinstance(rel, str) or not rel:
            raise _fail(where, f"{at}.path: expected a file path relative to the campaign folder")
        path = (root / rel).resolve()
        if path.suffix.lower() not in SCAN_EXTENSIONS:
            raise _fail(where, f"{at}.path: unsupported scan format {path.suffix!r} ({', '.join(SCAN_EXTENSIONS)})")
        if not path.is_file():
            raise _fail(where, f"{at}.path: file not found: {rel}")
        scans.append(_scan_entry(raw, sid, path, where, at, from_file, e57_cache))

    scans = _with_levelling(root, _drop_placeholder_poses(scans))

    pairs: list[PairEntry] = []
    raw_pairs = doc.get("pairs") or []
    if not isinstance(raw_pairs, list):
        raise _fail(where, "pairs: expected a list")
    seen_pairs: set[tuple[str, str]] = set()
    for i, raw in enumerate(raw_pairs):
        at = f"pairs[{i}]"
        if not isinstance(raw, dict):
            raise _fail(where, f"{at}: expected a mapping with scan, reference, a_priori")
        _unknown(raw, _PAIR_KEYS, where, f"{at}.")
        for key in ("scan", "reference"):
            ref = raw.get(key)
            ref = str(ref) if isinstance(ref, int) and not isinstance(ref, bool) else ref
            if ref not in seen:
                raise _fail(where, f"{at}.{key}: unknown scan id {ref!r}")
        s, r = str(raw["scan"]), str(raw["reference"])
        if s == r:
            raise _fail(where, f"{at}: scan and reference are the same scan {s!r}")
        if (s, r) in seen_pairs or (r, s) in seen_pairs:
            raise _fail(where, f"{at}: pair {s}-{r} is listed twice")
        seen_pairs.add((s, r))
        if "a_priori" not in raw:
            raise _fail(where, f"{at}.a_priori: missing (dx, dy, dz, dheading_deg)")
        prior4 = _numbers(raw["a_priori"], 4, where, f"{at}.a_priori")
        box = raw.get("search")
        if box is not None:
            from forestmap_assets.core.registration.pair_checks import search_box

            if not isinstance(box, dict):
                raise _fail(where, f"{at}.search: expected a mapping, e.g. {{along_deg: 90, across_m: 0.5}}")
            try:
                search_box((1.0, 1.0, 1.0), box)
            except ValueError as exc:
                raise _fail(where, f"{at}.{exc}") from None
            box = tuple((str(k), float(v)) for k, v in box.items())
        pairs.append(PairEntry(s, r, prior4, box))  # type: ignore[arg-type]

    search = doc.get("search")
    if search is not None:
        if not isinstance(search, dict):
            raise _fail(where, "search: expected a mapping with xy_m, z_m, heading_deg")
        _unknown(search, _SEARCH_KEYS, where, "search.")
        search = {k: _positive(v, where, f"search.{k}") for k, v in search.items()}

    step: float | tuple[float, float] | None = None
    beam: dict[str, float] = {}
    sensor = doc.get("sensor")
    if sensor is not None:
        if not isinstance(sensor, dict):
            raise _fail(where, "sensor: expected a mapping")
        _unknown(sensor, _SENSOR_KEYS, where, "sensor.")
        raw_step = sensor.get("angular_step_deg")
        if isinstance(raw_step, (list, tuple)):
            a, e = _numbers(raw_step, 2, where, "sensor.angular_step_deg")
            step = (_positive(a, where, "sensor.angular_step_deg[0]"), _positive(e, where, "sensor.angular_step_deg[1]"))
        elif raw_step is not None:
            step = _positive(raw_step, where, "sensor.angular_step_deg")
        # the beam (footprint diameter exit + divergence x range) sets the refinement's sigma
        # and the silhouette edges the DBH slice leaves out
        if sensor.get("beam_divergence_mrad") is not None:
            beam["beam_divergence_mrad"] = _non_negative(sensor["beam_divergence_mrad"], where,
                                                         "sensor.beam_divergence_mrad")
        if sensor.get("beam_exit_mm") is not None:
            beam["beam_exit_m"] = 1e-3 * _non_negative(sensor["beam_exit_mm"], where, "sensor.beam_exit_mm")

    overrides = doc.get("params") or {}
    if not isinstance(overrides, dict):
        raise _fail(where, "params: expected a mapping of stage -> {key: value}")
    # the search box and the beam are defaults of their stages' sections; params win
    # a named beam also gives the silhouettes' widths to the DBH (core/mapping/stem_calipers.py)
    trees_beam = {**beam, "calipers": True, "caliper_widening": "beam"} if beam else {}
    for section, values in (("registration", search or {}), ("refine", beam), ("trees", trees_beam)):
        if values:
            overrides = {**overrides, section: {**values, **(overrides.get(section) or {})}}
    try:
        params = resolve_params(environment, overrides)
    except ParamsError as exc:
        raise _fail(where, str(exc)) from None

    return Campaign(
        root=root,
        name=name.strip(),
        environment=environment,
        scans=tuple(scans),
        pairs=tuple(pairs),
        search=search,
        angular_step_deg=step,
        params=params,
    )
