"""OpenHTF phases mirroring a profile's steps, and ``build_test``.

Each measurement carries its unit and, as validators, exactly the profile limits
on that quantity (``in_range(low, high)``), so OpenHTF's verdict and gearbench's
own limit check (result.json) agree:

- calibrate_<m>: ``<m>_kt`` N·m/A (motors.<m>.Kt, and Kt_rel_datasheet limits times
  the datasheet Kt), ``<m>_kt_rel_datasheet`` 1
  (motors.<m>.Kt_rel_datasheet), ``<m>_inertia`` kg·m² (J), ``<m>_viscous``
  N·m·s/rad (D), ``<m>_coulomb`` N·m (Tc);
- load: no measurement (the operator mounts the reducer);
- efficiency: ``ratio`` 1, and per operating point ``eta_incremental_<w>rad_s_<T>Nm``
  and ``eta_absolute_<w>rad_s_<T>Nm`` (efficiency.eta_incremental / eta_absolute;
  w = input speed setpoint, T = output braking torque setpoint of the profile);
- gearbench_result: ``gearbench_status`` equals "passed"; result.json attached.

A value that is not a finite number is left unset (OpenHTF: UNSET, phase FAIL).
"""
from __future__ import annotations

import math
import signal
import threading
from pathlib import Path

from ..profile import CalibrateStep, EfficiencyStep, LoadStep, load_profile
from ._compat import htf, plain_argv
from .plugs import BenchPlug, SimBenchPlug

units = htf.units
with plain_argv():
    from openhtf.plugs.user_input import UserInput

MOTOR_QUANTITIES = (   # result key, measurement suffix, unit, description
    ("Kt", "kt", units.NEWTON_METRE_PER_AMPERE, "torque constant Kt (paper eq. 17, corrected)"),
    ("Kt_rel_datasheet", "kt_rel_datasheet", units.ONE, "Kt / datasheet Kt"),
    ("J", "inertia", units.KILOGRAM_METRE_SQUARED, "rotor inertia J"),
    ("D", "viscous", units.NEWTON_METRE_SECOND, "viscous friction D, N m s/rad"),
    ("Tc", "coulomb", units.NEWTON_METRE, "Coulomb friction torque Tc"),
)
EFFICIENCY_QUANTITIES = ("eta_incremental", "eta_absolute")


def measurement(profile, name: str, unit, doc: str, quantity: str, scaled: dict | None = None):
    """A Measurement with ``unit`` and one in_range validator per profile limit on
    ``quantity`` (and on each quantity of ``scaled``, its bounds times the factor)."""
    m = htf.Measurement(name).with_units(unit)
    names = []
    factors = {quantity: 1.0, **(scaled or {})}
    for lim in profile.limits:
        if lim.quantity in factors and (lim.low is not None or lim.high is not None):
            f = factors[lim.quantity]
            m = m.in_range(minimum=None if lim.low is None else lim.low * f,
                           maximum=None if lim.high is None else lim.high * f)
            names.append(lim.name)
    return m.doc(f"{doc} [{quantity}]" + (f"; profile limit {', '.join(names)}" if names else ""))


def point_name(quantity: str, speed_rad_s: float, torque_nm: float) -> str:
    return f"{quantity}_{speed_rad_s:g}rad_s_{torque_nm:g}Nm"


def _set(test, name: str, value) -> None:
    if value is not None and math.isfinite(value):
        test.measurements[name] = float(value)
    else:
        test.logger.warning("%s: no finite value (%r); left unset", name, value)


def _calibrate_phase(profile, index: int, step: CalibrateStep, name: str):
    m = step.motor
    kt_datasheet = profile.motors[m].kt_datasheet
    # a limit on Kt / datasheet also bounds Kt itself, in N m/A
    scaled = {"Kt": {f"motors.{m}.Kt_rel_datasheet": kt_datasheet}}
    meas = [measurement(profile, f"{m}_{suffix}", unit, f"motor {m}: {doc}", f"motors.{m}.{key}",
                        scaled.get(key)) for key, suffix, unit, doc in MOTOR_QUANTITIES]

    @htf.PhaseOptions(name=name)
    @htf.plug(bench=BenchPlug, prompts=UserInput)
    @htf.measures(*meas)
    def calibrate(test, bench, prompts):
        """Calibrate one motor: unloaded, then with the inertia disk."""
        b = bench.open(test.test_record.dut_id, prompts)
        bench.call(b.run_step, index)
        r = b.motors[m]
        values = {"Kt": r.kt_nm_per_a, "Kt_rel_datasheet": r.kt_nm_per_a / kt_datasheet,
                  "J": r.inertia_kgm2, "D": r.viscous_nm_s_per_rad, "Tc": r.coulomb_nm}
        for key, suffix, _, _ in MOTOR_QUANTITIES:
            _set(test, f"{m}_{suffix}", values[key])
    return calibrate


def _load_phase(index: int, name: str):
    @htf.PhaseOptions(name=name)
    @htf.plug(bench=BenchPlug, prompts=UserInput)
    def load(test, bench, prompts):
        """Mount the reducer between the motors."""
        bench.call(bench.open(test.test_record.dut_id, prompts).run_step, index)

    return load


def _efficiency_phase(profile, index: int, step: EfficiencyStep, name: str):
    grid = [(w, t) for w in step.speeds_in_rad_s for t in step.torques_out_nm]
    meas = [measurement(profile, "ratio", units.ONE, "reducer ratio n = input / output speed", "ratio")]
    meas += [measurement(profile, point_name(q, w, t), units.ONE,
                         f"{q} at {w:g} rad/s input, {t:g} N m output", f"efficiency.{q}")
             for w, t in grid for q in EFFICIENCY_QUANTITIES]

    @htf.PhaseOptions(name=name)
    @htf.plug(bench=BenchPlug, prompts=UserInput)
    @htf.measures(*meas)
    def efficiency(test, bench, prompts):
        """Efficiency map: input in speed control, output braking in current control."""
        b = bench.open(test.test_record.dut_id, prompts)
        n0 = len(b.points)
        bench.call(b.run_step, index)
        _set(test, "ratio", b.ratio)
        kt_out = b.kt_used("out")
        for p in b.points[n0:]:
            # the set torque of this level: its current command x the Kt that computed it
            torque = min(step.torques_out_nm, key=lambda t: abs(abs(p.out_command_a) * kt_out - t))
            for q in EFFICIENCY_QUANTITIES:
                _set(test, point_name(q, p.speed_setpoint_rad_s, torque), getattr(p, q))

    return efficiency


@htf.PhaseOptions(name="gearbench_result")
@htf.plug(bench=BenchPlug)
@htf.measures(htf.Measurement("gearbench_status").equals("passed")
              .doc("gearbench's own verdict: passed | failed | fault | aborted"))
def result_phase(test, bench):
    """Check the profile's limits, write the run folder, attach result.json."""
    r = bench.finish()
    test.measurements.gearbench_status = r.status
    path = Path(r.out_dir) / "result.json"
    if path.is_file():
        test.attach_from_file(str(path), "gearbench_result.json", mimetype="application/json")
    test.logger.info("gearbench run %s: %s, folder %s", r.run_id, r.status, r.out_dir)


def phases(profile_path) -> list:
    """The profile's steps as OpenHTF phases, plus ``gearbench_result``; their plug
    ``bench`` is the generic ``BenchPlug`` placeholder: substitute with
    ``[p.with_plugs(bench=SomePlug.for_profile(profile_path)) for p in phases(...)]``."""
    profile = load_profile(profile_path)
    out, seen = [], set()
    for i, step in enumerate(profile.steps):
        if isinstance(step, CalibrateStep):
            base = step.name or f"calibrate_{step.motor}"
        elif isinstance(step, LoadStep):
            base = step.name or "load"
        else:
            base = step.name or "efficiency"
        name, k = base, 2
        while name in seen:
            name, k = f"{base}_{k}", k + 1
        seen.add(name)
        if isinstance(step, CalibrateStep):
            out.append(_calibrate_phase(profile, i, step, name))
        elif isinstance(step, LoadStep):
            out.append(_load_phase(i, name))
        elif isinstance(step, EfficiencyStep):
            out.append(_efficiency_phase(profile, i, step, name))
    return out + [result_phase]


class GearbenchTest(htf.Test):
    """``openhtf.Test`` that never reads the station's ``sys.argv`` and installs
    OpenHTF's SIGINT handler (Ctrl-C aborts the test) only while it executes."""

    def configure(self, **kwargs) -> None:
        with plain_argv():
            super().configure(**kwargs)

    def execute(self, *args, **kwargs) -> bool:
        if threading.current_thread() is not threading.main_thread():
            return super().execute(*args, **kwargs)
        before = signal.signal(signal.SIGINT, htf.Test.handle_sig_int)
        try:
            return super().execute(*args, **kwargs)
        finally:
            signal.signal(signal.SIGINT, before)


def build_test(profile_path, sim: bool = False, *, out_root: str = "results/openhtf",
               seed: int | None = None, plug: type | None = None) -> GearbenchTest:
    """An OpenHTF test running ``profile_path``: real bench, or the simulated one (``sim``).

    ``plug``: your own BenchPlug subclass instead (e.g. a station's bench plug).
    Each execution writes a gearbench run folder under ``out_root``.
    """
    profile = load_profile(profile_path)
    base = plug or (SimBenchPlug if sim else BenchPlug)
    bound = base.for_profile(profile_path, out_root=str(out_root), seed=seed)
    nodes = [p.with_plugs(bench=bound) for p in phases(profile_path)]
    return GearbenchTest(*nodes, test_name=profile.name, gearbench_profile=str(profile.path),
                         gearbench_profile_sha256=profile.sha256, gearbench_sim=bool(sim))
