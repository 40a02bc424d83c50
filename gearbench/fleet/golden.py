"""Golden-unit check: a reference reducer, run now, against its stored baseline run.

A station keeps reference ("golden") units whose behaviour does not change; a
golden run that deviates from the unit's baseline beyond the two runs' combined
uncertainty points at the tester (motors, drives, couplings), not the unit.
``compare`` is pure; ``check_golden`` reads and writes the station database.
"""
from __future__ import annotations

import math
import sqlite3
from pathlib import Path
from ..analysis.calibration import motor_value
from ..station.database import connect

RATIO_REL_TOL = 0.002   # the ratio has no interval; 0.2 % is far above encoder resolution
Z95 = 1.959964


def _halfwidth(ci) -> float | None:
    if isinstance(ci, (list, tuple)) and len(ci) == 2 and None not in ci:
        return (float(ci[1]) - float(ci[0])) / 2
    return None


def _row(name, base, new, tol) -> dict:
    ok = None
    if base is not None and new is not None and tol is not None and math.isfinite(tol):
        ok = abs(new - base) <= tol
    return dict(quantity=name, baseline=base, value=new,
                delta=None if base is None or new is None else new - base, tolerance=tol, ok=ok)


def compare(baseline: dict, result: dict) -> list[dict]:
    """Quantity by quantity: |value - baseline| within the combined 95 % uncertainty of
    both runs (``ok`` None where a quantity carries no uncertainty to judge by)."""
    rows = []
    for m, b in (baseline.get("motors") or {}).items():
        n = (result.get("motors") or {}).get(m)
        if not n:
            rows.append(_row(f"motors.{m}.Kt", b.get("Kt"), None, None) | {"ok": False})
            continue
        hb, hn = _halfwidth(b.get("Kt_ci95")), _halfwidth(n.get("Kt_ci95"))
        rows.append(_row(f"motors.{m}.Kt", b.get("Kt"), n.get("Kt"),
                         math.hypot(hb, hn) if hb is not None and hn is not None else None))
        sb, sn = (b.get("fit") or {}).get("J_std"), (n.get("fit") or {}).get("J_std")
        rows.append(_row(f"motors.{m}.J", motor_value(b, "J"), motor_value(n, "J"),
                         Z95 * math.hypot(sb, sn) if sb is not None and sn is not None else None))
        cb, cn = (b.get("fit") or {}).get("loss_covariance"), (n.get("fit") or {}).get("loss_covariance")
        for k, key in enumerate(("D", "Tc")):
            tol = None
            if cb and cn:
                tol = Z95 * math.sqrt(max(cb[k][k], 0) + max(cn[k][k], 0))
            rows.append(_row(f"motors.{m}.{key}", motor_value(b, key), motor_value(n, key), tol))
    if baseline.get("ratio") is not None:
        rows.append(_row("ratio", baseline["ratio"], result.get("ratio"),
                         RATIO_REL_TOL * abs(baseline["ratio"])))
    new_pts = result.get("efficiency") or []
    for i, bp in enumerate(baseline.get("efficiency") or []):
        tag = f"efficiency[{bp.get('speed_setpoint_rad_s', bp.get('speed_in_rad_s', 0)):.0f}rad_s," \
              f"{bp.get('torque_out_nm', 0):.3g}Nm]"
        np_ = new_pts[i] if i < len(new_pts) else {}
        for key in ("eta_incremental", "eta_absolute"):
            hb, hn = _halfwidth(bp.get(f"{key}_ci95")), _halfwidth(np_.get(f"{key}_ci95"))
            rows.append(_row(f"{tag}.{key}", bp.get(key), np_.get(key),
                             math.hypot(hb, hn) if hb is not None and hn is not None else None))
    return rows


def mark_golden(db_path: str | Path, serial: str, profile: str) -> None:
    """Register ``serial`` as a reference unit for ``profile`` on this station."""
    con = connect(db_path)
    try:
        with con:
            con.execute("INSERT OR IGNORE INTO golden (serial, profile) VALUES (?, ?)", (serial, profile))
    finally:
        con.close()


def check_golden(db_path: str | Path, result: dict) -> dict:
    """Compare a golden run with its unit's baseline; the first passed golden run of a
    unit becomes its baseline. Returns ``{status, baseline_run_id, rows}`` with status
    baseline-set | matches | deviates | not-judged."""
    import json

    con = connect(db_path)
    try:
        serial, profile = result.get("serial"), result.get("profile")
        row = con.execute("SELECT baseline_run_id FROM golden WHERE serial = ? AND profile = ?",
                          (serial, profile)).fetchone()
        base_id = row[0] if row else None
        if result.get("status") != "passed":
            return dict(status="not-judged", baseline_run_id=base_id, rows=[],
                        reason=f"golden run ended {result.get('status')}; repeat it")
        if base_id is None:
            with con:
                con.execute("INSERT INTO golden (serial, profile, baseline_run_id, set_utc) "
                            "VALUES (?, ?, ?, ?) ON CONFLICT (serial, profile) DO UPDATE SET "
                            "baseline_run_id = excluded.baseline_run_id, set_utc = excluded.set_utc",
                            (serial, profile, result["run_id"], result.get("finished_utc")))
            return dict(status="baseline-set", baseline_run_id=result["run_id"], rows=[])
        got = con.execute("SELECT result_json FROM runs WHERE run_id = ?", (base_id,)).fetchone()
        if got is None:
            return dict(status="not-judged", baseline_run_id=base_id, rows=[],
                        reason=f"baseline run {base_id} is not in {db_path}")
        rows = compare(json.loads(got[0]), result)
        bad = [r for r in rows if r["ok"] is False]
        return dict(status="deviates" if bad else "matches", baseline_run_id=base_id, rows=rows)
    except sqlite3.Error as exc:
        return dict(status="not-judged", baseline_run_id=None, rows=[], reason=f"{db_path}: {exc}")
    finally:
        con.close()


def format_report(rep: dict) -> list[str]:
    lines = [f"Golden unit: {rep['status']}"
             + (f" (baseline run {rep['baseline_run_id']})" if rep.get("baseline_run_id") else "")
             + (f": {rep['reason']}" if rep.get("reason") else "")]
    for r in rep["rows"]:
        if r["value"] is None or r["baseline"] is None:
            lines.append(f"  MISSING {r['quantity']}")
            continue
        mark = {True: "ok     ", False: "DEVIATES", None: "(info) "}[r["ok"]]
        tol = f" tol ±{r['tolerance']:.4g}" if r["tolerance"] is not None else ""
        lines.append(f"  {mark} {r['quantity']:<44} {r['value']:.6g} vs {r['baseline']:.6g} "
                     f"(Δ {r['delta']:+.3g}{tol})")
    return lines
