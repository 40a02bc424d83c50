"""Shared test helpers."""
from __future__ import annotations

import json
import os
import shutil

import pytest

from gearbench import one_blas_thread

one_blas_thread()     # as every gearbench process does (gearbench.one_blas_thread says why)


def in_ci() -> bool:
    """True where ``.ci/run`` runs the suite (it installs the Debian tools the tests use)."""
    return os.environ.get("CI", "").lower() in ("1", "true", "yes")


def require_dev_data() -> None:
    """Skip (fail in CI, where ``../shared`` is always beside the clone) when the dev
    data sets are absent."""
    from gearbench.benchmarks._data import DEV_DIR

    if not (DEV_DIR / "truth.json").is_file():
        message = f"dev data not found at {DEV_DIR} (../shared/datasets/dev beside the checkout)"
        if in_ci():
            pytest.fail(message + " (CI provides ../shared; in CI this test must not be skipped)")
        pytest.skip(message)


@pytest.fixture(scope="session")      # before any module fixture that reads the data
def dev_data():
    """Use as ``pytest.mark.usefixtures("dev_data")`` on tests that read the dev data."""
    require_dev_data()


def assert_claimed_accuracy(result: dict, plant: dict, motors=("in", "out")) -> None:
    """A run's Kt and every efficiency point against the simulated plant's own truth (at
    the commanded operating points, ``gearbench.sim.truth.simulation_truth``), at the
    accuracy the README claims (``gearbench.benchmarks.robustness.TARGETS``)."""
    from gearbench.benchmarks.robustness import TARGETS
    from gearbench.sim.truth import simulation_truth

    truth = simulation_truth(plant, result["efficiency"])
    errors = []
    for m in motors:
        err = 100 * (result["motors"][m]["Kt"] / truth["motors"][m]["Kt"] - 1)
        if abs(err) > TARGETS["kt_pct"]:
            errors.append(f"motor {m}: Kt {err:+.3f} % (claimed <= {TARGETS['kt_pct']} %)")
    for p, t in zip(result["efficiency"], truth["efficiency"]):
        for kind, target in (("incremental", TARGETS["inc_pp"]), ("absolute", TARGETS["abs_pp"])):
            err = 100 * (p[f"eta_{kind}"] - t[f"eta_{kind}"])
            if abs(err) > target:
                errors.append(f"{p['in_command']:g} rad/s, {p['out_command']:.4g} A: {kind} η "
                              f"{err:+.3f} pp (claimed <= {target} pp)")
    assert not errors, "; ".join(errors)


def require_tool(name: str, install_hint: str) -> str:
    """Path of an external program, or skip (fail in CI) with a one-line reason.

    On a developer's machine with only python3 a test that needs, say, Debian's
    ``mbpoll`` is skipped with the install hint; in CI, where ``.ci/run`` installs it,
    its absence fails the test so it can never be skipped unnoticed where it matters.
    """
    exe = shutil.which(name)
    if exe is None:
        message = f"{name} is not installed; {install_hint}"
        if in_ci():
            pytest.fail(message + " (.ci/run installs it; in CI this test must not be skipped)")
        pytest.skip(message)
    return exe


@pytest.fixture(scope="session")
def cvt_sim_run(tmp_path_factory):
    """One full ``gearbench run cvt --sim --report --rrd`` (about a minute), shared by the
    tests that look at its report and its live view."""
    import subprocess
    import sys

    given = os.environ.get("GEARBENCH_TEST_CVT_RUN")
    if given:   # a finished cvt run folder with run.rrd (developers on a loaded host)
        out = tmp_path_factory.mktemp("given") / "cvt-run"
        shutil.copytree(given, out)
        (out / "report.html").unlink(missing_ok=True)
        p = subprocess.run([sys.executable, "-m", "gearbench", "report", str(out)], capture_output=True, text=True)
        assert p.returncode == 0 and (out / "run.rrd").is_file(), p.stderr
        return out
    # These tests look at the outputs, not at the bench: a bench fault (exit 3, e.g. the
    # emulator starved of CPU on a loaded host until the heartbeat watchdog trips) is
    # retried once with a new folder; its own tests are in test_run / test_cia402.
    for attempt in (1, 2):
        out = tmp_path_factory.mktemp("station") / "cvt-run"
        p = subprocess.run([sys.executable, "-m", "gearbench", "run", "cvt", "--sim", "--yes", "--quiet",
                            "--serial", "SIM-REPORT-1", "--out", str(out), "--rrd", str(out / "run.rrd"),
                            "--report", "--mdf"], capture_output=True, text=True, timeout=1800,
                           cwd=tmp_path_factory.getbasetemp())
        if p.returncode != 3:
            break
        print(f"cvt_sim_run: attempt {attempt} ended in a bench fault: "
              f"{json.loads((out / 'result.json').read_text()).get('reason', '')[:300]}")
    assert p.returncode == 0, p.stderr[-3000:]
    return out


def start_emulator(can: str):
    """``gearbench emulate --can CAN`` in a child process, once it says ``ready``."""
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-m", "gearbench", "emulate", "--can", str(can)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    ready = proc.stdout.readline().strip()
    assert ready == "ready", proc.stderr.read()
    return proc


def emulator_command(proc, cmd: dict) -> dict:
    """One fixture command (JSON line) to a ``gearbench emulate`` child, and its answer."""
    proc.stdin.write(json.dumps(cmd) + "\n")
    proc.stdin.flush()
    return json.loads(proc.stdout.readline())
