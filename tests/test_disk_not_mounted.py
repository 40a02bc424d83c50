"""An operator who forgets the disk must get a refusal, not a Kt made of noise."""
import subprocess
import sys

import pytest

from gearbench.benchmarks._data import DEV_DIR

DEV = DEV_DIR
U = DEV / "calib_motor_a_unloaded.csv"


@pytest.mark.usefixtures("dev_data")           # skipped without it, failed in CI
def test_same_inertia_in_both_runs_is_refused():
    p = subprocess.run([sys.executable, "-m", "gearbench", "calibrate", "--unloaded", str(U),
                        "--loaded", str(U), "--inertia", "1.5e-5", "--json"],
                       capture_output=True, text=True)
    assert p.returncode == 2, p.stdout
    assert "disk's inertia does not show" in p.stderr and "Traceback" not in p.stderr
    assert p.stdout == ""
