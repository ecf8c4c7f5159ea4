"""``levelling.yaml`` beside ``campaign.yaml``: the scans' roll and pitch that ``forestmap run``
estimated from their shared stems (:mod:`forestmap_assets.core.mapping.levelling`), written
when a scan was found tilted against the reference scan and the run went again with them.

A scan's estimate replaces its entry's ``tilt_deg`` while that entry still says what it said
when the estimate was made (``from_tilt_deg``); change the entry, or delete the file, and the
scans are levelled as ``campaign.yaml`` says (and estimated again)::

    reference: s1
    rounds: 1
    scans:
      s2: {tilt_deg: [0.318, 0.082], from_tilt_deg: [0.0, 0.0], sd_deg: 0.031}
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import yaml

LEVELLING_FILE = "levelling.yaml"
HEADER = ("# Written by forestmap run: each scan's roll and pitch (deg) estimated from the stems it\n"
          "# shares with the scans registered to it, replacing its campaign.yaml tilt_deg while that\n"
          "# still reads from_tilt_deg. Delete this file to level the scans as campaign.yaml says.\n")


def _pair(value, where: str) -> tuple[float, float]:
    ok = isinstance(value, (list, tuple)) and len(value) == 2
    if ok:
        try:
            out = (float(value[0]), float(value[1]))
        except (TypeError, ValueError):
            ok = False
        else:
            if all(math.isfinite(v) for v in out) and not any(isinstance(v, bool) for v in value):
                return out
    raise ValueError(f"{where}: expected two numbers (roll, pitch in degrees), got {value!r}")


def read_levelling(root: Path) -> tuple[dict[str, dict], int]:
    """The estimates of ``root/levelling.yaml`` (``{scan: {tilt_deg, from_tilt_deg, sd_deg}}``) and its
    rounds; ``({}, 0)`` without the file. A malformed file raises ``ValueError`` naming the
    file and the field."""
    path = Path(root) / LEVELLING_FILE
    if not path.is_file():
        return {}, 0
    try:
        doc = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise ValueError(f"{path}: not readable YAML ({str(exc).splitlines()[0]})") from None
    scans = doc.get("scans") if isinstance(doc, dict) else None
    if not isinstance(scans, dict):
        raise ValueError(f"{path}: scans: expected a mapping of scan id to tilt_deg and from_tilt_deg")
    rounds = doc.get("rounds", 1)
    if isinstance(rounds, bool) or not isinstance(rounds, int) or rounds < 0:
        raise ValueError(f"{path}: rounds: expected a whole number, got {rounds!r}")
    out = {}
    for sid, rec in scans.items():
        if not isinstance(rec, dict):
            raise ValueError(f"{path}: scans.{sid}: expected tilt_deg and from_tilt_deg")
        sd = rec.get("sd_deg", 0.0)
        if isinstance(sd, bool) or not isinstance(sd, (int, float)) or not math.isfinite(sd) or sd < 0:
            raise ValueError(f"{path}: scans.{sid}.sd_deg: expected a number >= 0, got {sd!r}")
        out[str(sid)] = {"tilt_deg": _pair(rec.get("tilt_deg"), f"{path}: scans.{sid}.tilt_deg"),
                         "from_tilt_deg": _pair(rec.get("from_tilt_deg"), f"{path}: scans.{sid}.from_tilt_deg"),
                         "sd_deg": float(sd)}
    return out, rounds


def write_levelling(root: Path, reference: str, scans: dict[str, dict], rounds: int) -> Path:
    """Write ``root/levelling.yaml`` atomically (``scans``: ``{scan: {tilt_deg, from_tilt_deg,
    sd_deg}}``)."""
    path = Path(root) / LEVELLING_FILE
    doc = {"reference": str(reference), "rounds": int(rounds),
           "scans": {str(s): {"tilt_deg": [round(float(v), 6) for v in r["tilt_deg"]],
                              "from_tilt_deg": [float(v) for v in r["from_tilt_deg"]],
                              "sd_deg": round(float(r.get("sd_deg", 0.0)), 6)}
                     for s, r in scans.items()}}
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(HEADER + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None))
    os.replace(tmp, path)
    return path
