"""``bench accuracy``'s real section: measured data with published parameters and
simulated robot joints with known truth, every identification form side by side.

* EMPS (Janot, Gautier & Brunot 2019, nonlinearbenchmark.org; files and published
  IDIM-LS values in ``shared/datasets/real-emps/README.md``) at 1 kHz and sliced to
  250 Hz and 100 Hz (every k-th sample, as a slower A/D would see it): M, Fv, Fc
  against the published values (the published σ is 0.1-0.6 %, so "within 2 %" is the
  target, as the issue sets it; the 95 % interval of our fit is printed beside).
* Robot joints (``_joint_sim``): slow reversing motion under a position loop, 100 Hz,
  load-side angle behind a gear, Coulomb ≥ 50 % of the rms current, gravity, ripple and
  a coloured disturbance; J, Fv, Fc against their truth, with "in" = truth inside the
  fit's 95 % interval.
* Robot joints from a second simulator (``_joint_stick_sim``: stiction, optional
  Stribeck friction, a PID position loop, two-sine or point-to-point motion with dwells),
  the default identification beside the textbook fit (``textbook_idim``): a family the
  identification was not developed on.
"""
from __future__ import annotations

import numpy as np

from ..analysis.identify import identify_default, physical_parameters
from ..analysis.uncertainty import coverage_factor
from ..trace import Trace
from ._data import SHARED_DIR
from ._joint_sim import JOINTS, simulate_joint
from ._joint_stick_sim import STICK_JOINTS, simulate_stick_joint

EMPS_DIR = SHARED_DIR / "datasets" / "real-emps"
EMPS_K = 2 * np.pi / 2.5e-3                 # motor rad per metre of travel
EMPS_PUBLISHED = {"M": 95.1089, "Fv": 203.5034, "Fc": 20.3935}
EMPS_TARGET_PCT = 2.0
FORMS = ("accel", "torque", "iv")


def physical(fit, gain: float) -> dict:
    """(inertia, viscous, Coulomb) = ``identify.physical_parameters`` with 95 % half-widths
    (``gain``: torque per ampere, or k for EMPS's motor angle in rad per metre)."""
    t = coverage_factor(fit.dof)
    return {k: (v, t * s) for k, (v, s) in zip(("J", "Fv", "Fc"), physical_parameters(fit, gain).values())}


def emps_rows(rates=(1000, 250, 100)) -> list[dict]:
    path = EMPS_DIR / "emps_train_motor_rad.csv"
    if not path.exists():
        return []
    tr = Trace.read(path)
    rows = []
    for rate in rates:
        k = int(round(1000 / rate))
        t, th, f = tr.time_s[::k], tr["position_rad"][::k], tr["current_a"][::k]
        for form in FORMS[:2]:        # no command recorded: no iv
            fit = identify_default(t, th, f, form=form, check=False, source=str(path))
            # motor-angle file: M = k/b2 (kg), Fv = (D/J)·k/b2, Fc = (Tc/J)/b2
            ph = physical(fit, EMPS_K)
            fc, fch = ph["Fc"][0] / EMPS_K, ph["Fc"][1] / EMPS_K
            vals = {"M": ph["J"], "Fv": ph["Fv"], "Fc": (fc, fch)}
            rows.append({"data": f"EMPS {rate} Hz", "form": form, "vals": vals,
                         "truth": EMPS_PUBLISHED, "cross": fit.extras["cross_check"]})
    return rows


def _joint_fit(d: dict, joint, form: str = "auto"):
    """The default identification of one simulated joint run (gravity terms where the
    joint carries gravity; the command as the iv form's instrument)."""
    return identify_default(d["time_s"], d["position_rad"], d["current_a"], form=form,
                            check=False, command=d["command"] if form == "iv" else None,
                            load_rad_per_unit=1.0 if joint.gravity_nm else None,
                            rad_per_unit=None)


def joint_rows(seeds=(0, 1, 2), forms=FORMS) -> list[dict]:
    rows = []
    for joint in JOINTS:
        for seed in seeds:
            d = simulate_joint(joint, seed=seed)
            truth = {"J": joint.J, "Fv": joint.Fv, "Fc": joint.Fc}
            for form in forms:
                fit = _joint_fit(d, joint, form)
                rows.append({"data": f"joint {joint.name} s{seed}", "form": form,
                             "group": f"joints {joint.name} {form}",
                             "vals": physical(fit, joint.gain_nm_a), "truth": truth,
                             "cross": fit.extras["cross_check"]})
    return rows


def joint_coverage(seeds) -> dict:
    """Coverage of the 95 % intervals of J, Fv and Fc over many seeds of both joint
    simulators at 100 Hz, per joint (the table's three seeds are too few to judge an
    interval by: the joints of one seed share its disturbance's draw) → {joint: {parameter:
    (covered, total)}}."""
    out: dict = {}
    rows = (joint_rows(seeds, forms=("torque",))
            + stick_joint_rows(seeds, rates=(100,), textbook=False))
    for r in rows:
        d = out.setdefault(r["group"], {})
        for name in ("J", "Fv", "Fc"):
            v, h = r["vals"][name]
            c, n = d.get(name, (0, 0))
            d[name] = (c + int(abs(v - r["truth"][name]) <= h), n + 1)
    return out


def textbook_idim(t: np.ndarray, q: np.ndarray, i: np.ndarray, gain: float, *,
                  cutoff_hz: float = 10.0, gravity: bool = False) -> dict:
    """The textbook inverse-dynamics least squares (IDIM-LS) a robotics engineer would run
    first: angle and current through one zero-phase 4th-order Butterworth low-pass,
    central differences, samples slower than 2 % of the top speed left out, then
    i = (J/K) q'' + (Fv/K) q' + (Fc/K) sign q' + c [+ sin q, cos q] by ordinary least
    squares; (J, Fv, Fc) = gain x the first three coefficients, with 95 % half-widths
    from the white-noise OLS covariance (what the textbook reports).

    References
    ----------
    M. Gautier, "Dynamic identification of robots with power model", Proc. IEEE ICRA 1997,
    pp. 1922-1927; W. Khalil and E. Dombre, "Modeling, Identification and Control of
    Robots", Hermes Penton 2002, ch. 12
    """
    from scipy.signal import butter, filtfilt

    dt = float(np.median(np.diff(t)))
    b, a = butter(4, cutoff_hz / (0.5 / dt))
    qf, i_f = filtfilt(b, a, q), filtfilt(b, a, i)
    w = np.gradient(qf, dt)
    acc = np.gradient(w, dt)
    moving = np.abs(w) > 0.02 * np.max(np.abs(w))
    cols = [acc, w, np.sign(w), np.ones_like(w)] + ([np.sin(qf), np.cos(qf)] if gravity else [])
    X, y = np.column_stack(cols)[moving], i_f[moving]
    beta, *_ = np.linalg.lstsq(X, y, rcond=None)
    e = y - X @ beta
    cov = np.linalg.inv(X.T @ X) * float(e @ e) / (len(y) - X.shape[1])
    half = coverage_factor(len(y) - X.shape[1]) * np.sqrt(np.diag(cov)[:3])
    return {k: (float(gain * v), float(gain * h)) for k, v, h in zip(("J", "Fv", "Fc"), beta[:3], half)}


def stick_joint_rows(seeds=(0, 1), rates=(100, 1000), textbook: bool = True) -> list[dict]:
    """The second simulator's joints, two motions, at 100 Hz and 1 kHz, the default beside
    the textbook."""
    rows = []
    for rate in rates:
        for joint in STICK_JOINTS:
            for motion in ("sine", "p2p"):
                for seed in seeds:
                    d = simulate_stick_joint(joint, motion=motion, seed=seed, rate_hz=rate)
                    fit = _joint_fit(d, joint)
                    label = f"{joint.name} {motion} s{seed} {rate:g}Hz"
                    family = f"joints (2nd sim) {rate:g} Hz"
                    rows.append({"data": label, "form": "default", "family": family,
                                 "group": f"2nd sim {rate:g} Hz {joint.name} {motion}",
                                 "vals": physical(fit, joint.gain_nm_a), "truth": d["truth"],
                                 "cross": fit.extras["cross_check"]})
                    if not textbook:
                        continue
                    rows.append({"data": label, "form": "textbook", "family": family,
                                 "vals": textbook_idim(d["time_s"], d["position_rad"],
                                                       d["current_a"], joint.gain_nm_a,
                                                       gravity=bool(joint.gravity_nm)),
                                 "truth": d["truth"], "cross": None})
    return rows


def print_real(rows: list[dict]) -> dict:
    """Table of errors (%) with 95 % half-widths; '*' = truth outside the interval;
    returns per family and form: [covered, total] over joints (inertia alone too) and the
    worst EMPS error."""
    print(f"\n{'real / joint data':<32}{'form':<9}{'inertia err %':>18}{'Fv err %':>18}"
          f"{'Fc err %':>18}   cross-check")
    score: dict = {}
    for r in rows:
        cells = []
        group = f"{r.get('family', 'joints')} {r['form']}"
        s = score.setdefault(group, {"covered": 0, "total": 0, "emps_max_pct": None,
                                   "inertia_covered": 0, "inertia_errors_pct": []})
        for (key, (v, h)), tv in zip(r["vals"].items(), r["truth"].values()):
            err, hw = 100 * (v / tv - 1), 100 * h / abs(tv)
            inside = abs(v - tv) <= h
            if r["data"].startswith("EMPS"):
                s["emps_max_pct"] = max(s["emps_max_pct"] or 0.0, abs(err))
            else:
                s["covered"] += inside
                s["total"] += 1
                if key == "J":
                    s["inertia_covered"] += inside
                    s["inertia_errors_pct"].append(abs(err))
            cells.append(f"{err:+8.2f} ±{hw:6.2f}{' ' if inside else '*'}")
        cc = r["cross"]
        verdict = "" if cc is None else "agree" if cc["agree"] else "DIFFER " + ",".join(cc["differ"])
        print(f"{r['data']:<32}{r['form']:<9}{''.join(f'{c:>18}' for c in cells)}   {verdict}")
    return score
