"""Operator-facing terminal output: progress on stderr while running; the summary table
and the verdict with the output folder on stdout at the end (``gearbench run … > log``
keeps what the unit got; ``--quiet`` keeps only the verdict line)."""
from __future__ import annotations

import sys
from typing import TextIO

from ..analysis.calibration import motor_value
from .records import (Calibration, EfficiencyPoint, Message, Progress, RunStart, RunStop,
                      StepStart, StepStop, Subscriber)


def _bar(frac: float, width: int = 24) -> str:
    n = int(round(max(0.0, min(1.0, frac)) * width))
    return "#" * n + "-" * (width - n)


class ProgressDisplay(Subscriber):
    """Progress on ``stream`` (stderr: a live bar on a terminal, plain lines otherwise);
    the end-of-run summary and verdict on ``summary`` (the command line's stdout; None: on
    ``stream``). ``quiet``: no progress and no table; only the verdict line, and that only
    when there is a ``summary`` stream (a quiet Python API call prints nothing)."""

    def __init__(self, stream: TextIO | None = None, quiet: bool = False,
                 summary: TextIO | None = None):
        self.out = stream or sys.stderr
        self.summary = summary
        self.tty = hasattr(self.out, "isatty") and self.out.isatty()
        self.quiet = quiet
        self._live = False
        self._slope_note = False

    def _line(self, text: str) -> None:
        if self.quiet:
            return
        if self._live:
            self.out.write("\r\033[K")
            self._live = False
        self.out.write(text + "\n")
        self.out.flush()

    def on_run_start(self, r: RunStart) -> None:
        self._line(f"gearbench: run {r.run_id} serial {r.serial or '-'} profile {r.profile_name}"
                   f"{' (SIMULATED bench)' if r.sim else ''} -> {r.out_dir}")

    def on_step_start(self, r: StepStart) -> None:
        self._line(f"  step {r.name}: {r.description}")

    def on_progress(self, r: Progress) -> None:
        if self.quiet or not self.tty:
            return
        eta = f" ETA {r.eta_s:5.0f} s" if r.eta_s is not None else ""
        self.out.write(f"\r\033[K  [{_bar(r.fraction_step)}] {r.step}: {r.point}  run {r.fraction_run:4.0%}{eta}")
        self.out.flush()
        self._live = True

    def on_step_stop(self, r: StepStop) -> None:
        lost = f", {r.lost_samples} lost (counted, never filled in: see result.json lost_at_sample)" if r.lost_samples else ""
        self._line(f"  step {r.name}: {r.status}, {r.n_samples} samples{lost}")

    def on_message(self, r: Message) -> None:
        tag = {"prompt": "OPERATOR", "warning": "WARNING", "error": "ERROR"}.get(r.level, "note")
        self._line(f"  {tag}: {r.text}")

    def on_calibration(self, r: Calibration) -> None:
        p = r.params
        lo, hi = (p.get("Kt_ci95") or [float("nan")] * 2)
        self._line(f"  motor {r.motor}: Kt = {p['Kt']:.5f} N m/A (95 % {lo:.5f}..{hi:.5f})")

    def on_efficiency_point(self, r: EfficiencyPoint) -> None:
        p = r.point
        if p.get("incremental_method") == "slope" and not self._slope_note:
            self._slope_note = True
            self._line("  (eta_incr: one slope of input on output current per speed, eq. 18 over "
                       "its staircase; each point's own secant is in result.json)")
        flag = "  loss extrapolated*" if p.get("loss_extrapolated") else ""
        self._line(f"  {p['speed_in_rad_s']:7.1f} rad/s {p['torque_out_nm']:7.3f} N m: "
                   f"eta_incr {p['eta_incremental']:.4f}  eta_abs {p['eta_absolute']:.4f}{flag}")

    def on_run_stop(self, r: RunStop) -> None:
        self._line("")
        if self.summary is None and self.quiet:
            return
        out = self.summary or self.out
        out.write((verdict_line(r.result) if self.quiet else summary_table(r.result)) + "\n")
        out.flush()


def _f(x, fmt: str) -> str:
    return "-" if x is None else format(x, fmt)


LIMIT_UNITS = {"Kt_rel_datasheet": "x datasheet", "Kt": "N m/A", "J": "kg m^2", "D": "N m s/rad",
               "Tc": "N m", "ratio": "1", "eta_incremental": "1", "eta_absolute": "1"}


def limit_unit(quantity: str) -> str:
    """The unit a limit's value is in (``motors.in.Kt_rel_datasheet`` is Kt over the
    datasheet value: "x datasheet")."""
    return LIMIT_UNITS.get((quantity or "").split(".")[-1], "")


VERDICTS = {"passed": "PASSED", "failed": "FAILED (limit)", "aborted": "ABORTED", "fault": "BENCH FAULT"}


def verdict_line(res: dict) -> str:
    """The one line that says what the unit got and where its record is."""
    verdict = VERDICTS.get(res.get("status"), str(res.get("status")).upper())
    sim = " SIMULATED" if res.get("simulation_truth") is not None or res.get("sim") else ""
    reason = f" — {res['reason']}" if res.get("reason") else ""
    return (f"Result:{sim} {verdict}{reason}  serial {res.get('serial') or '-'}  "
            f"exit {res.get('exit_code', '-')}  -> {res.get('out_dir') or '-'}")


def summary_table(res: dict) -> str:
    """The end-of-run table an operator reads: parameters, efficiency map, limits, verdict."""
    truth = res.get("simulation_truth") or {}
    lines = [f"Serial {res.get('serial') or '-'}  profile {res.get('profile')}  run {res.get('run_id')}"]
    lines.append(f"{'motor':<6}{'Kt N m/A':>11}{'95 % interval':>22}{'J kg m^2':>11}{'D N m s':>10}{'Tc N m':>9}"
                 + (f"{'Kt err':>9}" if truth else ""))
    for m, p in (res.get("motors") or {}).items():
        ci = p.get("Kt_ci95") or [None, None]
        err = ""
        if truth and m in truth.get("motors", {}):
            err = f"{100 * (p['Kt'] / truth['motors'][m]['Kt'] - 1):+8.3f}%"
        lines.append(f"{m:<6}{p['Kt']:>11.5f}  [{_f(ci[0], '.5f')}, {_f(ci[1], '.5f')}]"
                     f"{motor_value(p, 'J') or 0:>11.3e}{motor_value(p, 'D') or 0:>10.2e}"
                     f"{motor_value(p, 'Tc') or 0:>9.4f}{err:>9}")
    if res.get("ratio") is not None:
        tr = f"  (truth {truth['ratio']:.4f})" if truth.get("ratio") else ""
        lines.append(f"ratio n = {res['ratio']:.4f}{tr}")
    eff = res.get("efficiency") or []
    notes = []
    if eff:
        lines.append(f"{'speed rad/s':>12}{'torque N m':>11}{'eta_incr':>10}{'+-':>8}{'eta_abs':>9}"
                     + (f"{'err pp':>8}{'abs pp':>8}" if truth else ""))
        teff = truth.get("efficiency") or []
        for j, p in enumerate(eff):
            ci = p.get("eta_incremental_ci95") or [None, None]
            half = (ci[1] - ci[0]) / 2 if None not in ci else None
            row = (f"{p['speed_in_rad_s']:>12.1f}{p['torque_out_nm']:>11.3f}"
                   f"{p['eta_incremental']:>10.4f}{_f(half, '.4f'):>8}{_f(p.get('eta_absolute'), '.4f'):>9}")
            if j < len(teff):
                row += (f"{100 * (p['eta_incremental'] - teff[j]['eta_incremental']):>8.3f}"
                        f"{_pp(p.get('eta_absolute'), teff[j].get('eta_absolute')):>8}")
            if p.get("loss_extrapolated"):
                row += "  *"
            lines.append(row)
        notes.append("+- is the incremental efficiency's 95 % half-width.")
        if any(p.get("incremental_method") == "slope" for p in eff):
            notes.append("eta_incr is one value per speed: eq. 18 as the slope of input on output "
                         "current over that speed's staircase (each point's secant is in result.json).")
        if truth:
            notes.append("err pp / abs pp: measured minus the simulated plant's true incremental / "
                         "absolute efficiency, in percentage points.")
        if any(p.get("loss_extrapolated") for p in eff):
            notes.append("* loss extrapolated: the absolute efficiency uses a motor's friction "
                         "D w + Tc at a speed outside the speeds its calibration covered; let the "
                         "calibration waveform cover the map's speeds (docs/profile-authoring.md).")
    lims = res.get("limits") or []
    if lims:
        width = max(34, *(len(lim["name"]) + 1 for lim in lims))
        for lim in lims:
            unit = limit_unit(lim.get("quantity", ""))
            lines.append(f"  {'PASS' if lim['passed'] else 'FAIL'}  {lim['name']:<{width}} "
                         f"{_f(lim['value'], '.5g'):>10} {unit:<11} in [{_f(lim['low'], 'g')}, "
                         f"{_f(lim['high'], 'g')}]")
            if lim.get("reason"):
                lines.append(f"        {lim['reason']}")
    lines += [f"  {n}" for n in notes]
    lines.append(f"bench time {res.get('bench_time_s', 0):.1f} s, wall {res.get('wall_time_s', 0):.1f} s, "
                 f"{res.get('samples', 0)} samples, {res.get('lost_samples', 0)} lost")
    lines.append(verdict_line(res))
    return "\n".join(lines)


def _pp(measured, truth) -> str:
    if measured is None or truth is None:
        return "-"
    return f"{100 * (measured - truth):.3f}"
