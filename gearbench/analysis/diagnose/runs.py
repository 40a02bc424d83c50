"""A whole ``gearbench run`` diagnosed at once: every calibration trace per motor (the
single-motor diagnosis), every efficiency step against the reducer model built from
the run's own calibrations (result.json ``motors``), one summary — and the section of
the run's report.html as data and HTML.  Pure: the caller reads the files."""
from __future__ import annotations

import html

import numpy as np

from ...errors import GearbenchError
from ...trace import Trace
from .chain import diagnose
from .reducer import calibration, diagnose_bench

#: A motor whose travel in a calibration step is below this share of the step's
#: largest is idle there (parallel calibration moves one motor with the disk).
IDLE_SHARE = 0.01
#: Quantities a recorded step holds per motor (``<motor>.<quantity>`` columns).
_QUANTITIES = ("position_rad", "current_a", "command", "velocity_rad_s")


def _motor(step: Trace, motor: str) -> Trace:
    cols = {q: step[f"{motor}.{q}"] for q in _QUANTITIES if f"{motor}.{q}" in step}
    return Trace(step.time_s, cols, dict(step.meta), f"{step.source} [{motor}]")


def _bench(step: Trace, motor_in: str, motor_out: str) -> Trace:
    cols = {f"{side}_{q}": step[f"{m}.{q}"] for side, m in (("in", motor_in), ("out", motor_out))
            for q in _QUANTITIES if f"{m}.{q}" in step}
    return Trace(step.time_s, cols, dict(step.meta), step.source)


def _motors_in(step: Trace) -> list[str]:
    return sorted({n.split(".", 1)[0] for n in step.names if n.endswith(".position_rad")})


def _moving(tr: Trace) -> bool:
    th = np.asarray(tr["position_rad"], float)
    return bool(np.ptp(th) > 0 and np.ptp(np.asarray(tr["current_a"], float)) > 0)


def diagnose_run(steps: dict[str, Trace], result: dict, *, ratio: float | None = None,
                 motor_in: str = "in", motor_out: str = "out") -> dict:
    """Diagnose every recorded step of a run.

    Parameters
    ----------
    steps : dict of str to Trace
        Step name -> recorded trace (``<motor>.position_rad``, ``<motor>.current_a``...).
    result : dict
        The run's result.json (its ``motors`` calibrations build the reducer model).
    ratio : float, optional
        Gear ratio for the load-torque candidate of single-motor steps.
    motor_in, motor_out : str
        Names of the reducer's input and output motors.

    Returns
    -------
    dict
        ``steps``: one entry per diagnosed (step, motor) or (step, bench) with its
        nominal gap, chain, remainder and verdict; ``worst_gap_ratio`` and
        ``unknown_effects`` over the run; ``skipped`` with reasons.
    """
    motors = result.get("motors") or {}
    cals, out, skipped = {}, [], []
    for m, data in motors.items():
        try:
            cals[m] = calibration(data, f"result.json motors.{m}")
        except GearbenchError as exc:
            skipped.append({"step": "calibration", "motor": m, "why": str(exc)})
    for name, step in steps.items():
        present = _motors_in(step)
        if name.startswith("calibrat"):
            spans = {m: float(np.ptp(np.asarray(step[f"{m}.position_rad"], float)))
                     for m in present}
            for m in present:
                tr = _motor(step, m)
                # a motor idle in this step (the other one calibrated) holds still: its
                # few counts identify nothing (Kt/J came out -1390 on one)
                if not _moving(tr) or spans[m] < IDLE_SHARE * max(spans.values()):
                    skipped.append({"step": name, "motor": m,
                                    "why": "idle in this step (it did not move)"})
                    continue
                d = diagnose(tr, ratio=ratio).as_dict()
                out.append(_entry(name, m, "motor", d, d["remaining"], d["nominal"]["fit"]))
        elif motor_in in present and motor_out in present:
            ci, co = cals.get(motor_in), cals.get(motor_out)
            d = diagnose_bench(_bench(step, motor_in, motor_out), motor_in=ci,
                               motor_out=co).as_dict()
            worst = max(d["remaining"].values(), key=lambda r: r["gap_ratio"])
            entry = _entry(name, f"{motor_in}->{motor_out}", "bench", d, worst,
                           {"gap_ratio": max(d["nominal"][r]["gap_ratio"]
                                             for r in ("kinematics", "torque"))})
            entry["calibrated"] = bool(ci and co)
            entry["physical"] = d["nominal"].get("physical")
            out.append(entry)
        else:
            skipped.append({"step": name, "why": f"motors {present}: neither a calibration "
                                                 f"nor an {motor_in}->{motor_out} bench step"})
    return {"steps": out, "skipped": skipped,
            "worst_gap_ratio": max((e["gap_ratio_after"] for e in out), default=None),
            "unknown_effects": [f"{e['step']} {e['motor']}" for e in out if e["unknown_effect"]]}


def _entry(step: str, motor: str, kind: str, d: dict, rem: dict, fit: dict) -> dict:
    return {"step": step, "motor": motor, "kind": kind,
            "gap_ratio_nominal": float(fit["gap_ratio"]),
            "chain": [{"effect": c["effect"], "shrink_heldout": c["shrink_heldout"],
                       "params": c.get("params_final", c["params"]),
                       "confused_with": c.get("confused_with") or []} for c in d["chain"]],
            "verdict": (d.get("verdict") or {}).get("effect"),
            "gap_ratio_after": float(rem["gap_ratio"]),
            "at_noise_floor": bool(rem["at_noise_floor"]),
            "unknown_effect": bool(rem["unknown_effect"]),
            "diagnosis": d}


def report_section(run: dict) -> dict:
    """The run diagnosis as the report.html section: a title, one row per diagnosed
    step and the HTML of it (``html``).  Hook: the run report calls this with what
    ``diagnose_run`` returned and appends ``html`` to its body."""
    rows = [{"step": e["step"], "motor": e["motor"], "kind": e["kind"],
             "nominal": f"{e['gap_ratio_nominal']:.2f}x",
             "chain": ", ".join(f"{c['effect']} ({c['shrink_heldout']:.0%})"
                                for c in e["chain"]) or "—",
             "left": f"{e['gap_ratio_after']:.2f}x",
             "state": ("at the noise floor" if e["at_noise_floor"] else
                       "UNKNOWN EFFECT" if e["unknown_effect"] else "above the floor")}
            for e in run["steps"]]
    head = ("<tr><th>step</th><th>motor</th><th>model</th><th>nominal vs noise floor</th>"
            "<th>effects (held-out shrink)</th><th>left</th><th></th></tr>")
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(r[k]))}</td>" for k in
                                     ("step", "motor", "kind", "nominal", "chain", "left",
                                      "state")) + "</tr>" for r in rows)
    text = ("<h2>Diagnosis: where the model and the bench disagree</h2>"
            "<p class='note'>Each trace simulated over short held-out horizons from the "
            "measured current; the gap is the error above the data's own noise floor.</p>"
            f"<table>{head}{body}</table>")
    return {"title": "Diagnosis", "rows": rows, "html": text}
