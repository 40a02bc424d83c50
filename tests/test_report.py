"""The per-unit report as a quality engineer sees it: report.html of a real simulated
run, opened in headless Chromium — no console errors, every image loaded, the
numbers of result.json on the page; a screenshot is kept."""
from __future__ import annotations

import json
import subprocess
import sys
import time

import pytest

from browser import SCREENSHOTS, browser_factory  # noqa: F401  (fixture)
from gearbench import __version__
from gearbench.cli import main


def test_report_renders_in_chromium(cvt_sim_run, browser_factory):  # noqa: F811
    report = cvt_sim_run / "report.html"
    assert report.is_file(), "gearbench run --report wrote no report.html"
    html = report.read_text()
    assert "http://" not in html and "https://" not in html and "<script" not in html  # self-contained
    res = json.loads((cvt_sim_run / "result.json").read_text())

    t0 = time.monotonic()
    b = browser_factory(width=1200, height=1000)
    b.navigate(report.as_uri())
    b.pump(1.0)
    images = b.evaluate("[...document.images].map(i => ({alt: i.alt, w: i.naturalWidth, "
                        "h: i.naturalHeight, done: i.complete}))")
    text = b.evaluate("document.body.innerText")
    shot = b.screenshot(SCREENSHOTS / f"report-{res['serial']}.png", full_page=True)
    print(f"\nreport: {len(images)} images, browser {time.monotonic() - t0:.1f} s, screenshot {shot}")

    assert b.errors == [], b.errors
    alts = [i["alt"] for i in images]
    assert all(i["done"] and i["w"] > 0 and i["h"] > 0 for i in images), images
    assert "efficiency map" in alts
    assert {"identification fit motor in", "identification fit motor out"} <= set(alts)
    assert sum(a.startswith("trace ") for a in alts) == len(res["steps"])
    for needle in (res["serial"], res["profile_sha256"], "PASSED", __version__,
                   f"version {res['method_version']}", res["station"]["name"],
                   f"{res['motors']['in']['Kt']:.5g}", f"{res['ratio']:.6g}",
                   res["prompts"][0]["prompt"], "kt_in"):
        assert str(needle) in text, needle
    assert shot.stat().st_size > 50_000
    # the verdict badge itself says SIMULATED, next to PASSED, in the viewport a person sees first
    badges = b.evaluate("[...document.querySelectorAll('.verdict')].map(e => ({t: e.innerText, "
                        "top: e.getBoundingClientRect().top, bg: getComputedStyle(e).backgroundColor}))")
    assert [x["t"] for x in badges] == ["PASSED", "SIMULATED"], badges
    assert all(x["top"] < 200 for x in badges) and badges[0]["bg"] != badges[1]["bg"]
    # the extrapolated-loss flag is explained where it is shown
    if any(p.get("loss_extrapolated") for p in res["efficiency"]):
        assert "extrapolated motor loss: the absolute efficiency" in text


def test_report_pdf_and_bad_folder(cvt_sim_run, tmp_path, capsys):
    from browser import chromium_path

    chromium_path()   # skips (fails in CI) without chromium
    out = tmp_path / "r.html"
    assert main(["report", str(cvt_sim_run), "--out", str(out), "--pdf"]) == 0
    assert out.read_text().startswith("<!DOCTYPE html>")
    assert (tmp_path / "r.pdf").read_bytes()[:5] == b"%PDF-"
    _check_page_furniture(tmp_path / "r.pdf", json.loads((cvt_sim_run / "result.json").read_text()))
    p = subprocess.run([sys.executable, "-m", "gearbench", "report", str(tmp_path / "nowhere")],
                       capture_output=True, text=True)
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert "not a run folder" in p.stderr


@pytest.mark.parametrize("missing", ["result.json"])
def test_report_of_a_folder_without_result_is_one_line(tmp_path, missing):
    (tmp_path / "run").mkdir()
    p = subprocess.run([sys.executable, "-m", "gearbench", "report", str(tmp_path / "run")],
                       capture_output=True, text=True)
    assert p.returncode == 2 and missing in p.stderr and "Traceback" not in p.stderr


def test_view_opens_the_report_where_there_is_a_display(cvt_sim_run, monkeypatch):
    from gearbench.commands import view

    opened = []
    monkeypatch.setattr("webbrowser.open", lambda url: opened.append(url) or True)
    monkeypatch.setenv("DISPLAY", ":99")
    view._open_report(cvt_sim_run)
    assert opened == [(cvt_sim_run / "report.html").resolve().as_uri()]
    monkeypatch.delenv("DISPLAY")
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    view._open_report(cvt_sim_run)
    assert len(opened) == 1 or not sys.platform.startswith("linux")


def _check_page_furniture(pdf, res):
    """A4 pages, each with the serial, the verdict (SIMULATED) and 'page n of N'; no page
    ends on a heading alone (the efficiency map's and the fits' headings stay with them)."""
    pypdf = pytest.importorskip("pypdf")
    pages = pypdf.PdfReader(pdf).pages
    assert len(pages) >= 2
    for n, page in enumerate(pages, 1):
        w, h = float(page.mediabox.width), float(page.mediabox.height)
        assert (round(w), round(h)) == (595, 842), (w, h)          # A4 in points, not US Letter
        text = page.extract_text()
        assert res["serial"] in text and "PASSED · SIMULATED" in text, (n, text[:200])
        assert f"page {n} of {len(pages)}" in text, (n, text[-300:])
        # a figure's heading is on the page of its figure (the figures are images; the headings text)
        heads = sum(1 for x in text.splitlines()
                    if x.strip().startswith(("Eﬃciency map", "Efficiency map", "Identiﬁcation ﬁt",
                                             "Identification fit", "Traces")))
        assert len(page.images) >= heads, (n, heads, len(page.images))


def test_coinciding_speed_lines_stay_visible():
    """A harmonic drive's efficiency hardly depends on speed: three identical lines must
    still show three colours (markers, dashes and a small side-by-side offset), not one."""
    import io

    import matplotlib.image
    import numpy as np

    from gearbench.reports.plots import SPEED_COLOURS, efficiency_map_png

    pts = [{"speed_setpoint_rad_s": s, "speed_in_rad_s": s, "torque_out_nm": t, "eta_incremental": 0.8,
            "eta_incremental_ci95": [0.79, 0.81], "eta_absolute": 0.6, "eta_absolute_ci95": [0.59, 0.61]}
           for s in (100.0, 200.0, 300.0) for t in (5.0, 10.0, 15.0, 20.0)]
    img = (matplotlib.image.imread(io.BytesIO(efficiency_map_png(pts))) * 255).astype(int)
    h = img.shape[0]
    plot = img[:int(0.75 * h)]            # the axes, not the legend below them
    counts = []
    for c in SPEED_COLOURS[:3]:
        rgb = np.array([int(c[i:i + 2], 16) for i in (1, 3, 5)])
        counts.append(int(np.all(np.abs(plot[..., :3] - rgb) <= 25, axis=-1).sum()))
    assert min(counts) > 0.25 * max(counts), counts
