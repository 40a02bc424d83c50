"""The live view as a person sees it: the .rrd of a real simulated run, served by
``rerun --serve-web`` and rendered by Rerun's web viewer in headless Chromium
(software WebGL, SwiftShader). The screenshot is kept and checked by its pixels:
the motor current is drawn on its own axis (its trace spans the panel, not a flat
line at zero under a 300 rad/s velocity), so is the output motor's current setpoint (its
braking staircase, apart from its speed setpoints), and the efficiency series (Rerun's own,
one per input speed in the report's colours) are on screen.

WebAssembly start-up and software rendering take about a minute on 2 idle cores
and much longer on a loaded host; the test waits up to ``LIVE_VIEW_TIMEOUT_S``.
"""
from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.parse
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from browser import SCREENSHOTS, browser_factory  # noqa: F401  (fixture)
from gearbench.reports.plots import SPEED_COLOURS

LIVE_VIEW_TIMEOUT_S = float(os.environ.get("GEARBENCH_LIVE_VIEW_TIMEOUT_S", 900))
CURRENT_RGB = (228, 26, 28)          # gearbench.reports.live.rerun_view: current series colour
COMMAND_A_RGB = (152, 78, 163)       # ... and the current setpoint's
WIDTH, HEIGHT = 1280, 800


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _rgb(hex_colour: str) -> tuple[int, int, int]:
    return tuple(int(hex_colour[i:i + 2], 16) for i in (1, 3, 5))


def _mask(img: np.ndarray, rgb, tol: int = 40) -> np.ndarray:
    return np.all(np.abs(img[..., :3].astype(int) - np.array(rgb)) <= tol, axis=-1)


def what_is_drawn(png: Path) -> dict:
    """Pixel facts of a screenshot of the default layout (gearbench.reports.live.blueprint:
    two motor columns of 2/6.4 of the width each and the results on the right in the top
    5/9.2 of the height; the efficiency series below them, across the width; the log last)."""
    import matplotlib.image

    img = (matplotlib.image.imread(png) * 255).astype(np.uint8)
    h, w = img.shape[:2]
    top = int(0.05 * h), int(0.58 * h)            # the motor panels
    per_panel = (top[1] - top[0]) / 5             # motor out has five (two setpoint panels)
    # motor 'in', current panel: first column, its first panel
    panel = img[top[0]:top[0] + int(1.15 * (top[1] - top[0]) / 4), :int(0.30 * w)]
    rows = np.flatnonzero(_mask(panel, CURRENT_RGB).any(axis=1))
    spread = (rows.max() - rows.min()) / panel.shape[0] if rows.size else 0.0
    # motor 'out', current setpoint (its braking staircase in A): a panel of its own, where
    # the staircase spans the height (on a rad/s axis it would be a flat line)
    out_col = img[top[0]:top[1], int(0.32 * w):int(0.61 * w)]
    rows = np.flatnonzero(_mask(out_col, COMMAND_A_RGB, tol=30).any(axis=1))
    command_a = (rows.max() - rows.min()) / per_panel if rows.size else 0.0
    # the efficiency series (Rerun's own plot): a series per input speed, report colours
    below = img[int(0.58 * h):int(0.84 * h), :]
    speeds = [int(_mask(below, _rgb(c), tol=30).sum()) for c in SPEED_COLOURS[:3]]
    return {"current_spread": float(spread), "command_a_spread": float(command_a),
            "efficiency_series_pixels": speeds}


def _wait_port(port: int, server, t0: float) -> None:
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=2).close()
            return
        except OSError:
            assert server.poll() is None, "rerun --serve-web exited"
            assert time.monotonic() - t0 < 60, f"rerun gRPC port {port} not open in 60 s"
            time.sleep(0.5)


@pytest.mark.slow   # ~60 s of WebAssembly start-up and software rendering on 2 cores
def test_live_view_in_rerun_web_viewer(cvt_sim_run, browser_factory, tmp_path):  # noqa: F811
    rerun = shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))
    web, grpc = _free_port(), _free_port()
    server = subprocess.Popen([rerun, "--serve-web", "--bind", "127.0.0.1", "--web-viewer-port", str(web),
                               "--port", str(grpc), str(cvt_sim_run / "run.rrd")],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                              env={**os.environ, "RERUN_ANALYTICS": "0"}, cwd=tmp_path,
                              start_new_session=True)   # the wrapper and the viewer binary: one group
    shot = tmp_path / "poll.png"      # the kept copy is written once, at the end
    t0 = time.monotonic()
    try:
        while True:
            try:
                urllib.request.urlopen(f"http://127.0.0.1:{web}/", timeout=2).read()
                break
            except OSError:
                assert server.poll() is None, "rerun --serve-web exited"
                assert time.monotonic() - t0 < 60, "rerun web viewer did not come up in 60 s"
                time.sleep(0.5)
        url = (f"http://127.0.0.1:{web}/?url="
               + urllib.parse.quote(f"rerun+http://127.0.0.1:{grpc}/proxy", safe=""))
        _wait_port(grpc, server, t0)
        b = browser_factory(width=WIDTH, height=HEIGHT, webgl=True)
        b.navigate(url, timeout_s=120)
        facts, previous, same, reloads = {}, None, 0, 0
        while time.monotonic() - t0 < LIVE_VIEW_TIMEOUT_S:
            b.pump(10)
            b.screenshot(shot)
            facts = what_is_drawn(shot)
            data = shot.read_bytes()
            done = (facts["current_spread"] > 0.3 and facts["command_a_spread"] > 0.3
                    and min(facts["efficiency_series_pixels"]) > 30)
            same = same + 1 if data == previous else 0
            if done and same:                 # everything loaded and the picture settled
                break
            if same >= 3 and reloads < 3:     # stuck (e.g. on the welcome page: the viewer's
                b.navigate(url, timeout_s=120)  # gRPC connect timed out on a loaded host)
                reloads += 1
            previous = data
        kept = SCREENSHOTS / "live-view.png"
        kept.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(shot, kept)
        print(f"\nlive view: {time.monotonic() - t0:.0f} s to a settled picture ({reloads} reloads), "
              f"{facts}, screenshot {kept}")
    finally:
        os.killpg(server.pid, signal.SIGTERM)
        try:
            server.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(server.pid, signal.SIGKILL)
    # the current spans its own panel (a flat line would be a few pixels high)
    assert facts["current_spread"] > 0.3, (facts, shot)
    # the output motor's current setpoint has its own axis: the staircase spans its panel
    assert facts["command_a_spread"] > 0.3, (facts, shot)
    # the efficiency is Rerun's own series, one per input speed (the report's colours)
    assert min(facts["efficiency_series_pixels"]) > 30, (facts, shot)
