"""Operator-facing terminal output: progress bars while running, a summary table at the end."""
from __future__ import annotations

import sys
from typing import TextIO

from .records import (Calibration, EfficiencyPoint, Message, Progress, RunStart, RunStop,
                      StepStart, StepStop, Subscriber)


def _bar(frac: float, width: int = 24) -> str:
    n = int(round(max(0.0, min(1.0, frac)) * width))
    return "#" * n + "-" * (width - n)


class ProgressDisplay(Subscriber):
    """Progress on stderr: a live bar on a terminal, plain lines otherwise."""

    def __init__(self, stream: TextIO | None = None, quiet: bool = False):
        self.out = stream or sys.stderr
        self.tty = hasattr(self.out, "isatty") and self.out.isatty()
        self.quiet = quiet
        self._live = False

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
                   f"{' (simulated bench)' if r.sim else ''} -> {r.out_dir}")

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
        self._line(f"  {p['speed_in_rad_s']:7.1f} rad/s {p['torque_out_nm']:7.3f} N m: "
                   f"eta_incr {p['eta_incremental']:.4f}  eta_abs {p['eta_absolute']:.4f}")

    def on_run_stop(self, r: RunStop) -> None:
        self._line("")
        if not self.quiet:
            self.out.write(summary_table(r.result) + "\n")
            self.out.flush()


def _f(x, fmt: str) -> str:
    return "-" if x is None else format(x, fmt)


def summary_table(res: dict) -> str:
    """The end-of-run table an operator reads: parameters, efficiency map, limits, verdict."""
    truth = res.get("simulation_truth") or {}
    lines = [f"Serial {res.get('serial') or '-'}  profile {res.get('profile')}  run {res.get('run_id')}"]
    lines.append(f"{'motor':<6}{'Kt N m/A':>11}{'95 % interval':>22}{'J kg m^2':>11}{'D':>10}{'Tc N m':>9}"
                 + (f"{'Kt err':>9}" if truth else ""))
    for m, p in (res.get("motors") or {}).items():
        ci = p.get("Kt_ci95") or [None, None]
        err = ""
        if truth and m in truth.get("motors", {}):
            err = f"{100 * (p['Kt'] / truth['motors'][m]['Kt'] - 1):+8.3f}%"
        lines.append(f"{m:<6}{p['Kt']:>11.5f}  [{_f(ci[0], '.5f')}, {_f(ci[1], '.5f')}]"
                     f"{p.get('J', 0):>11.3e}{p.get('D', 0):>10.2e}{p.get('Tc', 0):>9.4f}{err:>9}")
    if res.get("ratio") is not None:
        tr = f"  (truth {truth['ratio']:.4f})" if truth.get("ratio") else ""
        lines.append(f"ratio n = {res['ratio']:.4f}{tr}")
    eff = res.get("efficiency") or []
    if eff:
        lines.append(f"{'speed rad/s':>12}{'torque N m':>11}{'eta_incr':>10}{'+-':>8}{'eta_abs':>9}"
                     + (f"{'err pp':>8}{'abs pp':>8}" if truth else ""))
        teff = truth.get("efficiency") or []
        for j, p in enumerate(eff):
            ci = p.get("eta_incremental_ci95") or [None, None]
            half = (ci[1] - ci[0]) / 2 if None not in ci else None
            row = (f"{p['speed_in_rad_s']:>12.1f}{p['torque_out_nm']:>11.3f}"
                   f"{p['eta_incremental']:>10.4f}{_f(half, '.4f'):>8}{p['eta_absolute']:>9.4f}")
            if j < len(teff):
                row += (f"{100 * (p['eta_incremental'] - teff[j]['eta_incremental']):>8.3f}"
                        f"{100 * (p['eta_absolute'] - teff[j]['eta_absolute']):>8.3f}")
            lines.append(row)
    for lim in res.get("limits") or []:
        lines.append(f"  {'PASS' if lim['passed'] else 'FAIL'}  {lim['name']:<34} {_f(lim['value'], '.5g'):>10}"
                     f"  in [{_f(lim['low'], 'g')}, {_f(lim['high'], 'g')}]")
    lines.append(f"bench time {res.get('bench_time_s', 0):.1f} s, wall {res.get('wall_time_s', 0):.1f} s, "
                 f"{res.get('samples', 0)} samples, {res.get('lost_samples', 0)} lost")
    verdict = {"passed": "PASSED", "failed": "FAILED (limit)", "aborted": "ABORTED",
               "fault": "BENCH FAULT"}.get(res.get("status"), str(res.get("status")).upper())
    lines.append(f"Result: {verdict}" + (f" — {res['reason']}" if res.get("reason") else ""))
    return "\n".join(lines)
