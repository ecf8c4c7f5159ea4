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

from forestmap_assets.params import Params, ParamsError, resolve_params

MANIFEST = "campaign.yaml"
SCAN_ID = re.compile(r"^[A-Za-z0-9_-]+$")
SCAN_EXTENSIONS = (".npz", ".e57", ".las", ".laz", ".ply", ".pcd", ".xyz", ".txt", ".csv")

_TOP_KEYS = {"name", "environment", "scans", "pairs", "search", "params", "sensor"}
_SCAN_KEYS = {"id", "path", "tilt_deg", "a_priori"}
_PAIR_KEYS = {"scan", "reference", "a_priori", "search"}
_SEARCH_KEYS = {"xy_m", "z_m", "heading_deg"}
_SENSOR_KEYS = {"angular_step_deg"}


class CampaignError(ValueError):
    """An invalid campaign folder or manifest; the message is one line naming file and field."""


@dataclass(frozen=True)
class ScanEntry:
    """One scan position of the campaign."""

    id: str
    path: Path
    tilt_deg: tuple[float, float] = (0.0, 0.0)
    a_priori: tuple[float, float, float, float] | None = None


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
        key = re.sub(r"[^A-Za-z0-9_]", "_", self.name)
        return key if key and not key[0].isdigit() else f"c_{key}"

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
        h = hashlib.sha256()
        with open(entry.path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        h.update(repr((entry.tilt_deg, self.angular_step_deg)).encode())
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


def _unknown(keys: Any, allowed: set[str], where: str, prefix: str) -> None:
    extra = sorted(set(keys) - allowed)
    if extra:
        raise _fail(where, f"{prefix}{extra[0]}: unknown key (allowed: {', '.join(sorted(allowed))})")


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
        tilt = _numbers(raw.get("tilt_deg", [0.0, 0.0]), 2, where, f"{at}.tilt_deg")
        prior = raw.get("a_priori")
        prior_t = _numbers(prior, 4, where, f"{at}.a_priori") if prior is not None else None
        scans.append(ScanEntry(sid, path, (tilt[0], tilt[1]), prior_t))  # type: ignore[arg-type]

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

    overrides = doc.get("params") or {}
    if not isinstance(overrides, dict):
        raise _fail(where, "params: expected a mapping of stage -> {key: value}")
    if search:
        reg = dict(overrides.get("registration") or {})
        for k, v in search.items():
            reg.setdefault(k, v)
        overrides = {**overrides, "registration": reg}
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
