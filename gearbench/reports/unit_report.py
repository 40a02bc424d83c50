"""The per-unit report: one self-contained ``report.html`` a quality engineer files with
the unit (images embedded, no external files, prints on A4).

Built from a finished run folder only (``result.json`` and the ``trace-*.parquet``
files), so it can be made again at any time: ``gearbench report RUN_DIR``.
"""
from __future__ import annotations

import base64
import html
import json
import re
from pathlib import Path

from .. import __version__
from ..errors import GearbenchError
from ..station.results import finite_or_none
from ..analysis.calibration import motor_value
from ..analysis.model_check import torque_balance
from ..station.recorder import load_step_trace
from .plots import efficiency_map_png, torque_fit_png, trace_thumbnail_png

_CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,sans-serif;margin:24px auto;max-width:1050px;color:#222}
h1{font-size:22px;margin:0 0 4px} h2{font-size:17px;border-bottom:1px solid #ccc;padding-bottom:3px;margin-top:28px}
table{border-collapse:collapse;font-size:13px;margin:6px 0} td,th{border:1px solid #ccc;padding:3px 8px;text-align:left}
th{background:#f2f2f2} td.num{text-align:right;font-variant-numeric:tabular-nums}
.verdict{display:inline-block;padding:6px 16px;border-radius:4px;font-size:20px;font-weight:bold;color:#fff}
.passed{background:#1a7f37} .failed,.fault,.aborted{background:#b42318}
.pass{color:#1a7f37;font-weight:bold} .fail{color:#b42318;font-weight:bold}
img{max-width:100%;border:1px solid #ddd} .thumbs{display:flex;flex-wrap:wrap;gap:8px}
.thumbs figure{margin:0;width:330px} figcaption{font-size:11px;color:#555}
.note{font-size:12px;color:#555} code{font-size:12px}
.sim{background:#6e40c9;margin-left:8px} .nowrap{white-space:nowrap} .hash{word-break:break-all;font-size:11px}
.footnote{font-size:12px;color:#444;border-left:3px solid #d4a72c;padding:2px 8px;margin:6px 0}
.page-furniture{display:none}
@media print{
 body{margin:0;max-width:none;font-size:11px} h1{font-size:18px} h2{font-size:14px;margin-top:16px}
 h2,h3{break-after:avoid-page;page-break-after:avoid}
 img,figure,.keep{break-inside:avoid;page-break-inside:avoid} tr{break-inside:avoid}
 .keep img{display:block;max-height:230mm;width:auto;max-width:100%}
 section{break-inside:auto} .keep-with-next{break-after:avoid-page}
 .thumbs figure{width:48%} figcaption{break-before:avoid}
}
"""

# A4 with the unit's serial, the verdict and "page n of N" on every printed page (CSS paged
# media margin boxes; Chromium >= 131 prints them; older ones print the page without them)
_PAGE_CSS = """
@page{{size:A4;margin:16mm 12mm 16mm 12mm;
 @top-left{{content:"gearbench efficiency test · {serial}";font:9px system-ui,sans-serif;color:#555}}
 @top-right{{content:"{verdict}";font:bold 9px system-ui,sans-serif;color:#555}}
 @bottom-left{{content:"run {run_id} · {started}";font:9px system-ui,sans-serif;color:#555}}
 @bottom-right{{content:"page " counter(page) " of " counter(pages);font:9px system-ui,sans-serif;color:#555}}}}
"""


def _css_string(text) -> str:
    """Text safe inside a CSS string in a <style> element."""
    return re.sub(r'["\\<>\n]', " ", str(text or ""))


def _e(x) -> str:
    return html.escape("" if x is None else str(x))


_num = finite_or_none


def _f(v, fmt: str = ".5g", scale: float = 1.0) -> str:
    f = _num(v)
    return "–" if f is None else format(f * scale, fmt)


def _ci(ci, fmt=".5g", scale=1.0) -> str:
    if isinstance(ci, (list, tuple)) and len(ci) == 2:
        return f"[{_f(ci[0], fmt, scale)}, {_f(ci[1], fmt, scale)}]"
    return "–"


def _img(png: bytes, alt: str) -> str:
    return f'<img alt="{_e(alt)}" src="data:image/png;base64,{base64.b64encode(png).decode()}">'


def _table(header: list[str] | None, rows: list[list[str]], num_cols: tuple[int, ...] = ()) -> str:
    head = f"<tr>{''.join(f'<th>{_e(h)}</th>' for h in header)}</tr>" if header else ""
    body = "".join("<tr>" + "".join(f'<td class="num">{c}</td>' if j in num_cols else f"<td>{c}</td>"
                                    for j, c in enumerate(r)) + "</tr>" for r in rows)
    return f"<table>{head}{body}</table>"


def load_run(run_dir: str | Path) -> dict:
    """result.json of a run folder; a clear error naming the file otherwise."""
    d = Path(run_dir)
    if not d.is_dir():
        raise GearbenchError(f"{d}: not a run folder; give the --out folder of 'gearbench run'")
    p = d / "result.json"
    try:
        result = json.loads(p.read_text())
    except FileNotFoundError:
        raise GearbenchError(f"{p}: missing; is {d} the output folder of a 'gearbench run'?") from None
    except (OSError, ValueError) as exc:
        raise GearbenchError(f"{p}: unreadable ({exc}); re-run the test or restore the file") from None
    if not isinstance(result, dict) or "status" not in result:
        raise GearbenchError(f"{p}: not a gearbench result (no 'status'); give a run folder")
    return result


def _traces(run_dir: Path) -> dict:

    out = {}
    for p in sorted(run_dir.glob("trace-*.parquet"), key=lambda p: p.stat().st_mtime):
        try:
            out[p.stem[len("trace-"):]] = load_step_trace(p)
        except Exception:   # a damaged trace must not hide the rest of the report
            continue
    return out


def _motor_section(result: dict, traces: dict) -> str:

    motors = result.get("motors") or {}
    if not motors:
        return "<h2>Motors</h2><p class='note'>No motor was calibrated in this run.</p>"
    rows = []
    for m, p in motors.items():
        rows.append([_e(m), _f(p.get("Kt")), _ci(p.get("Kt_ci95")), _f(motor_value(p, "J")), _f(motor_value(p, "D")),
                     _f(motor_value(p, "Tc")), _e(p.get("method", ""))])
    parts = ["<h2>Motors: torque constant Kt (paper eq. 17, from two inertias)</h2>",
             _table(["motor", "Kt [N·m/A]", "Kt 95 % interval", "J [kg·m²]", "D [N·m·s/rad]",
                     "Tc [N·m]", "method"], rows, (1, 2, 3, 4, 5))]
    truth = (result.get("simulation_truth") or {}).get("motors") or {}
    if truth:
        parts.append("<p class='note'>Simulated bench: true Kt "
                     + ", ".join(f"{_e(m)} {_f(t.get('Kt'))} N·m/A (error {_f(100 * (motors[m]['Kt'] / t['Kt'] - 1), '+.3f')} %)"
                                 for m, t in truth.items() if m in motors and _num(t.get('Kt'))) + "</p>")
    # motors calibrated at once share a step (calibrate-in.out-...): each motor's own run
    # ends where result.json's measurements say
    ends = {(x.get("segment"), x.get("motor")): x.get("run_samples")
            for x in result.get("measurements") or [] if x.get("kind") == "calibrate"}
    for m, p in motors.items():
        runs = []
        disk = _num((p.get("fit") or {}).get("disk_inertia_kgm2")) or 0.0
        for step, tr in traces.items():
            parts_ = step.split("-")
            if (parts_[0] != "calibrate" or len(parts_) < 3 or m not in parts_[1].split(".")
                    or f"{m}.position_rad" not in tr):
                continue
            end = ends.get((step, m))
            if end:
                tr = tr.slice(0, int(end))
            loaded = not step.endswith("-unloaded")
            try:
                b = torque_balance(tr.time_s, tr[f"{m}.position_rad"], tr[f"{m}.current_a"],
                                   Kt=p["Kt"], J=motor_value(p, "J"), D=motor_value(p, "D"), Tc=motor_value(p, "Tc"),
                                   disk_kgm2=disk if loaded else 0.0)
            except Exception:
                continue
            runs.append((f"with disk ({disk:.3g} kg·m²)" if loaded else "alone", b))
        if runs:
            # heading and figure one block: a printed page never ends on the heading alone
            parts.append(f"<div class='keep'><h3>Identification fit, motor {_e(m)}: measured vs model</h3>"
                         + _img(torque_fit_png(runs, motor=m, kt=p["Kt"], kt_ci95=p.get("Kt_ci95")),
                                f"identification fit motor {m}") + "</div>")
    return "\n".join(parts)


def _efficiency_section(result: dict) -> str:

    pts = result.get("efficiency") or []
    ratio = result.get("ratio")
    parts = ["<h2>Reducer</h2>",
             f"<p>Measured reduction ratio n = <b>{_f(ratio, '.6g')}</b></p>"]
    if not pts:
        return "\n".join(parts)
    parts.append("<div class='keep'><h2>Efficiency map</h2>"
                 + _img(efficiency_map_png(pts, result.get("limits") or []), "efficiency map") + "</div>")
    rows = []
    for p in pts:
        flag = "extrapolated motor loss *" if p.get("loss_extrapolated") else ""
        rows.append([_f(p.get("speed_setpoint_rad_s") or p.get("speed_in_rad_s"), ".4g"),
                     _f(p.get("speed_in_rad_s"), ".5g"), _f(p.get("torque_out_nm"), ".4g"),
                     _f(p.get("eta_incremental"), ".2f", 100), _ci(p.get("eta_incremental_ci95"), ".2f", 100),
                     _f(p.get("eta_absolute"), ".2f", 100), _ci(p.get("eta_absolute_ci95"), ".2f", 100),
                     _e(flag)])
    parts.append(_table(["ω_in set [rad/s]", "ω_in [rad/s]", "T_out [N·m]", "η_inc [%]", "95 %",
                         "η_abs [%]", "95 %", "note"], rows, (0, 1, 2, 3, 4, 5, 6)))
    if any(p.get("incremental_method") == "slope" for p in pts):
        parts.append("<p class='note'>η_inc is one value per input speed: eq. 18 as the slope of input "
                     "on output current over that speed's torque staircase (each point's own secant "
                     "is in result.json).</p>")
    ext = [p for p in pts if p.get("loss_extrapolated")]
    if ext:
        rng = ", ".join(f"motor {m}: {_f(r[0], '.4g')}–{_f(r[1], '.4g')} rad/s"
                        for m, r in (("in", ext[0].get("loss_speed_range_in_rad_s")),
                                     ("out", ext[0].get("loss_speed_range_out_rad_s")))
                        if isinstance(r, (list, tuple)) and len(r) == 2)
        parts.append("<p class='footnote'>* <b>extrapolated motor loss</b>: the absolute efficiency "
                     "subtracts each motor's own friction D·ω + Tc, identified from its calibration runs; "
                     f"at these points a motor turned faster or slower than its calibration covered "
                     f"({_e(rng) or 'range not recorded'}), so its friction is extrapolated and the "
                     "absolute efficiency's interval is widened. The incremental efficiency (eq. 18) does "
                     "not use the friction and is unaffected. Fix: let the calibration waveform cover the "
                     "map's speeds (docs/profile-authoring.md, “Calibration covering the map”).</p>")
    return "\n".join(parts)


def _limits_section(result: dict) -> str:
    lims = result.get("limits") or []
    if not lims:
        why = " (the run stopped before limits were checked)" if result.get("status") in ("fault", "aborted") else ""
        return f"<h2>Limits</h2><p class='note'>No limits checked{_e(why)}.</p>"
    rows = [[_e(x.get("name")), _e(x.get("quantity", "")), _f(x.get("value")), _f(x.get("low")),
             _f(x.get("high")),
             '<span class="pass">PASS</span>' if x.get("passed") else '<span class="fail">FAIL</span>']
            for x in lims]
    n_fail = sum(1 for x in lims if not x.get("passed"))
    return (f"<h2>Limits: {len(lims) - n_fail} of {len(lims)} passed</h2>"
            + _table(["limit", "quantity", "value", "low", "high", "result"], rows, (2, 3, 4)))


def _samples_section(result: dict, traces: dict) -> str:

    steps = result.get("steps") or {}
    lost = result.get("lost_samples_by_step") or {}
    rows = [[_e(s), str(n), str(lost.get(s, "–"))] for s, n in steps.items()]
    rows.append(["<b>total</b>", str(result.get("samples", "–")), str(result.get("lost_samples", "–"))])
    parts = ["<h2>Samples</h2>",
             "<p class='note'>Samples lost on the bus are counted per step; up to 1 % of a step is "
             "filled by interpolation for the analysis, more is refused.</p>",
             _table(["step", "samples", "lost"], rows, (1, 2))]
    parts.append(_measurements_table(result))
    thumbs = []
    for step, tr in traces.items():
        cols = {n: tr[n] for n in tr.names if n.endswith((".velocity_rad_s", ".current_a"))}
        if cols and len(tr) > 1:
            thumbs.append(f"<figure>{_img(trace_thumbnail_png(tr.time_s, cols, title=step), f'trace {step}')}"
                          f"<figcaption>trace-{_e(step)}.parquet, {len(tr)} samples</figcaption></figure>")
    if thumbs:
        # the heading stays with the first row of thumbnails
        parts += [f"<div class='thumbs'><h2 style='width:100%;margin-bottom:0'>Traces</h2>{''.join(thumbs)}</div>"]
    return "\n".join(parts)


def _measurements_table(result: dict) -> str:
    """Adaptive measurements: how long each took, the statistical interval it reached and
    why it stopped (docs/profile-format.md, "Adaptive measurement")."""
    ms = result.get("measurements") or []
    if not ms:
        return ""
    rows = []
    for m in ms:
        cal = m.get("kind") == "calibrate"
        reached = m.get("interval_reached")
        shown = "–" if reached is None else (f"{100 * reached:.3g} %" if cal else f"{reached:.3g} pp")
        target = f"{100 * m['target']:.3g} %" if cal else f"{m['target']:.3g} pp"
        settle = "" if cal or m.get("settle_s") is None else f"{m['settle_s']:.2f}" + (
            "" if m.get("settled_in_time", True) else " (not settled)")
        rows.append([_e(m.get("name", "")), f"{m.get('duration_s', 0):.2f}", settle, shown, target,
                     _e(m.get("stopped_by", ""))])
    return ("<h2>Measurements: adaptive stop</h2><p class='note'>Each measurement ran until the "
            "statistical part of its 95 % interval met the profile's target (Kt: this run's share, "
            "relative; efficiency: the speed's slope), or to its max_s.</p>"
            + _table(["measurement", "s", "settle s", "reached", "target", "stopped by"], rows, (1, 2, 3, 4)))


def _header(result: dict, run_dir: Path) -> str:
    status = str(result.get("status", "?"))
    station = result.get("station") or {}
    rows = [
        ("serial", result.get("serial")),
        ("profile", f"{result.get('profile', '')} ({result.get('profile_path', '')})"),
        ("profile sha256", result.get("profile_sha256")),
        ("station", " · ".join(str(x) for x in (station.get("name"), station.get("host")) if x) or "–"),
        ("start (UTC)", result.get("started_utc")),
        ("end (UTC)", result.get("finished_utc")),
        ("bench time / wall time", f"{_f(result.get('bench_time_s'), '.1f')} s / {_f(result.get('wall_time_s'), '.1f')} s"),
        ("gearbench (run)", result.get("gearbench_version", "– (not recorded)")),
        ("analysis method", f"{result.get('method', '')} version {result.get('method_version', '–')}"),
        ("run id", result.get("run_id")),
        ("run folder", str(run_dir)),
    ]
    sim = _simulated(result)
    if sim:
        rows.append(("bench", "SIMULATED (--sim): numbers are from the emulated bench"))
    verdict = status.upper()
    reason = f" — {_e(result.get('reason'))}" if result.get("reason") else ""
    badge = ("<span class='verdict sim' title='measured on the simulated bench (--sim), not on a "
             "real unit'>SIMULATED</span>") if sim else ""
    nowrap = {"start (UTC)", "end (UTC)", "run id"}
    cells = [[f"<b>{_e(k)}</b>",
              f"<span class='nowrap'>{_e(v)}</span>" if k in nowrap else
              f"<span class='hash'>{_e(v)}</span>" if k == "profile sha256" else _e(v)] for k, v in rows]
    head = (f"<h1>Efficiency test report · {_e(result.get('serial'))}</h1>"
            f"<p><span class='verdict {_e(status)}'>{_e(verdict)}</span>{badge}{reason}</p>"
            + _table(None, cells))
    prompts = result.get("prompts") or []
    if prompts:
        who = {"AutoOperator": "answered automatically (--yes / simulated bench)",
               "TerminalOperator": "confirmed at the terminal"}
        head += "<h2>Operator prompts</h2>" + _table(
            ["prompt", "shown (UTC)", "confirmed (UTC)", "by"],
            [[_e(p.get("prompt")), _when(p.get("shown_utc")), _when(p.get("confirmed_utc")),
              _e(who.get(p.get("operator"), p.get("operator")))] for p in prompts])
    return head


def _when(ts) -> str:
    """A UTC timestamp that may wrap between date and time, never inside either."""
    text = _e(ts)
    date, sep, time = text.partition("T")
    if not sep:
        return f"<span class='nowrap'>{text}</span>"
    return f"<span class='nowrap'>{date}</span> <span class='nowrap'>{time}</span>"


def _diagnosis_section(run_dir: Path) -> str:
    """The section `gearbench diagnose RUN_DIR` left in the run (diagnosis.json); none
    when the run was not diagnosed, a note when the file cannot be read."""
    from ..analysis.diagnose.runs import report_section

    p = run_dir / "diagnosis.json"
    if not p.exists():
        return ""
    try:
        return f"<section>{report_section(json.loads(p.read_text()))['html']}</section>"
    except (OSError, ValueError, KeyError, TypeError) as exc:
        return (f"<section><h2>Diagnosis</h2><p class='note'>{_e(p)} unreadable ({_e(exc)}); "
                f"run 'gearbench diagnose {_e(run_dir)}' again.</p></section>")


def _simulated(result: dict) -> bool:
    return bool(result.get("simulation_truth")) or bool(result.get("sim"))


def build_report(run_dir: str | Path) -> str:
    """The report of one run folder as one HTML string (images inline)."""
    d = Path(run_dir)
    result = load_run(d)
    traces = _traces(d)
    body = "\n".join([_header(result, d), _limits_section(result), _motor_section(result, traces),
                      _efficiency_section(result), _samples_section(result, traces),
                      _diagnosis_section(d)])
    title = f"gearbench report {result.get('serial', '')} {result.get('started_utc', '')}"
    verdict = str(result.get("status", "?")).upper() + (" · SIMULATED" if _simulated(result) else "")
    page = _PAGE_CSS.format(serial=_css_string(result.get("serial")), verdict=_css_string(verdict),
                            run_id=_css_string(result.get("run_id")),
                            started=_css_string(result.get("started_utc")))
    return (f"<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'><title>{_e(title)}</title>"
            f"<style>{_CSS}{page}</style></head><body>\n{body}\n"
            f"<p class='note'>Report made by gearbench {_e(__version__)} from {_e(d / 'result.json')}.</p>"
            "</body></html>\n")


def write_report(run_dir: str | Path, out: str | Path | None = None) -> Path:
    """Write ``report.html`` (default: into the run folder); returns its path."""
    d = Path(run_dir)
    text = build_report(d)
    p = Path(out) if out else d / "report.html"
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        tmp = p.with_name(p.name + ".tmp")
        tmp.write_text(text, encoding="utf-8")
        tmp.replace(p)
    except OSError as exc:
        raise GearbenchError(f"{p}: cannot write the report ({exc.strerror}); choose a writable --out") from None
    return p


def find_chromium() -> str | None:
    import shutil

    for name in ("chromium", "chromium-browser", "google-chrome", "chrome"):
        exe = shutil.which(name)
        if exe:
            return exe
    return None


def write_pdf(html_path: Path, pdf_path: Path) -> Path:
    """Print the report to PDF with a headless Chromium (Debian: apt-get install chromium)."""
    import subprocess

    exe = find_chromium()
    if exe is None:
        raise GearbenchError("--pdf needs Chromium to print the report; install it "
                             "(Debian: apt-get install chromium) or open report.html and print it")
    cmd = [exe, "--headless", "--no-sandbox", "--disable-gpu", "--no-pdf-header-footer",
           f"--print-to-pdf={pdf_path.resolve()}", html_path.resolve().as_uri()]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    if p.returncode != 0 or not pdf_path.exists():
        last = (re.sub(r"\s+", " ", p.stderr.strip().splitlines()[-1]) if p.stderr.strip() else "")
        raise GearbenchError(f"{pdf_path}: Chromium could not print the report ({last}); "
                             f"open report.html and print it instead")
    return pdf_path
