"""Run results as files a factory uses: ``result.json`` and ``junit.xml``.

Both are written by one subscriber when the run stops (also after an abort or a
fault, so a partial run still leaves its record).
"""
from __future__ import annotations

import json
import math
import xml.etree.ElementTree as ET
from pathlib import Path

from .records import RunStop, Subscriber


def finite_or_none(v) -> float | None:
    """A finite float, or None (missing, NaN, a boolean, not a number)."""
    if v is None or isinstance(v, bool) or type(v).__name__ == "bool_":
        return None
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


NOISE_REL = 1e-12           # in a list of numbers, |x| below this x the largest is rounding noise


def round_floats(o):
    """``o`` with rounding noise in lists of numbers set to 0 (as ``_clean``), the rest
    unchanged: the result a run returns is then exactly what result.json, the station and
    the central database hold. (Digits are not rounded: results are compared exactly
    between the typed records, result.json and the databases.)"""
    if isinstance(o, dict):
        return {k: round_floats(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        out = [round_floats(v) for v in o]
        nums = [abs(v) for v in out if isinstance(v, float) and math.isfinite(v)]
        if len(nums) > 1:
            floor = NOISE_REL * max(nums)
            out = [0.0 if isinstance(v, float) and abs(v) < floor else v for v in out]
        return out if isinstance(o, list) else type(o)(out) if not hasattr(o, "_fields") else out
    return o


def _clean(o):
    """JSON-safe: numpy scalars to Python, NaN/inf to null (strict JSON); in a list of
    numbers (a range, an interval) a value that is rounding noise beside the others (a
    speed range's -2.8e-14 beside 241) is 0."""
    if isinstance(o, dict):
        return {str(k): _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        out = [_clean(v) for v in o]
        nums = [abs(v) for v in out if isinstance(v, float)]
        if len(nums) > 1:
            floor = NOISE_REL * max(nums)
            out = [0.0 if isinstance(v, float) and abs(v) < floor else v for v in out]
        return out
    if hasattr(o, "item") and not isinstance(o, (str, bytes)):
        try:
            o = o.item()
        except (ValueError, AttributeError):
            o = o.tolist()
    if isinstance(o, float) and not math.isfinite(o):
        return None
    return o


def as_written(result: dict) -> dict:
    """The result exactly as result.json holds it (JSON-safe: NaN as null, list noise 0)."""
    return _clean(result)


def write_result_json(path: str | Path, result: dict) -> Path:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(_clean(result), indent=2, allow_nan=False) + "\n")
    tmp.replace(p)  # atomic: a reader never sees half a file
    return p


def write_junit(path: str | Path, result: dict) -> Path:
    """One testcase per limit; an aborted/faulted run adds an errored testcase."""
    limits = result.get("limits", [])
    failures = sum(1 for lim in limits if not lim.get("passed"))
    errors = 1 if result.get("status") in ("aborted", "fault") else 0
    suite = ET.Element("testsuite", name=f"gearbench.{result.get('profile', 'run')}",
                       tests=str(len(limits) + errors), failures=str(failures), errors=str(errors),
                       time=f"{result.get('wall_time_s', 0.0):.3f}",
                       timestamp=str(result.get("started_utc", "")))
    props = ET.SubElement(suite, "properties")
    for key in ("serial", "profile", "profile_sha256", "run_id"):
        ET.SubElement(props, "property", name=key, value=str(result.get(key, "")))
    for lim in limits:
        case = ET.SubElement(suite, "testcase", classname=f"gearbench.{result.get('serial', '')}",
                             name=lim["name"])
        if not lim.get("passed"):
            f = ET.SubElement(case, "failure", message=(
                lim["reason"] if lim.get("reason") else
                f"{lim['name']} = {lim.get('value')} outside [{lim.get('low')}, {lim.get('high')}]"))
            f.text = json.dumps(_clean(lim))
    if errors:
        case = ET.SubElement(suite, "testcase", classname="gearbench", name="run")
        e = ET.SubElement(case, "error", message=str(result.get("reason", result.get("status"))))
        e.text = str(result.get("reason", ""))
    p = Path(path)
    ET.ElementTree(suite).write(
        p, encoding="utf-8", xml_declaration=True)
    return p


class ResultWriter(Subscriber):
    """Writes result.json and junit.xml into the run folder at RunStop."""

    def __init__(self, out_dir: str | Path):
        self.out_dir = Path(out_dir)

    def on_run_stop(self, rec: RunStop) -> None:
        write_result_json(self.out_dir / "result.json", rec.result)
        write_junit(self.out_dir / "junit.xml", rec.result)
