"""Fault-injection cases for the diagnoser's scorecard and tests (test scaffolding: it
lives here, outside the pure, I/O-free analysis package).

Injection harness: each effect, at several amplitudes and under several excitations,
put into the simulated motor (``gearbench.sim.simulate_motor``) and diagnosed blind.

The diagnoser sees only ``time_s, position_rad, current_a, command`` (truth, the
drive's velocity estimate and the simulation metadata are stripped).  The base motor
has every effect off (the paper's model plus the drive, sensors and noise); clean
controls are that base motor.  ``inertia_mismatch`` is diagnosed against the motor's
own model (Kt, J, D without the added disk) given as the nominal, as a user with an
earlier calibration would.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..analysis.diagnose.reducer import BENCH_COLUMNS
from ..analysis.diagnose.nominal import GivenModel
from ..analysis.diagnose.chain import Diagnosis, diagnose
from ..sim import MotorParams, simulate_motor, waveforms
from ..trace import Trace

DURATION_S = 6.0
EXCITATIONS = ("multisine", "reversing", "sweep_slow")
#: Broadband excitation (log chirp to 80 Hz): reaches shaft resonances the 0.3-6 Hz
#: excitations above cannot; not in the default set (the scorecard adds it on request).
BROADBAND = "chirp"

#: effect -> (MotorParams changes per amplitude level low/moderate/high, extra kwargs)
INJECTIONS: dict[str, list[dict]] = {
    "coulomb_friction": [{"Tc": 0.002}, {"Tc": 0.005}, {"Tc": 0.01}],
    "stribeck_friction": [{"Ts": 0.002}, {"Ts": 0.005}, {"Ts": 0.01}],
    "cogging": [{"cog_amp": 0.0005}, {"cog_amp": 0.0015}, {"cog_amp": 0.003}],
    "torque_ripple": [{"ripple_amp": 0.02}, {"ripple_amp": 0.05}, {"ripple_amp": 0.1}],
    "current_offset": [{"current_offset_a": 0.01}, {"current_offset_a": 0.03},
                       {"current_offset_a": 0.08}],
    "time_delay": [{"delay_samples": 1}, {"delay_samples": 2}, {"delay_samples": 4}],
    "kt_saturation": [{"kt_sat_a": 3.0}, {"kt_sat_a": 1.5}, {"kt_sat_a": 0.8}],
    # direction- / position-dependent friction ride on a Coulomb friction (they vary it)
    "direction_friction": [{"Tc": 0.005, "Tc_asym": 0.001},
                           {"Tc": 0.005, "Tc_asym": 0.002, "D_asym": 5e-7},
                           {"Tc": 0.008, "Tc_asym": 0.004, "D_asym": 9e-7}],
    "position_friction": [{"Tc": 0.005, "Tc_pos_amp": 0.2, "Tc_pos_order": 2},
                          {"Tc": 0.005, "Tc_pos_amp": 0.5, "Tc_pos_order": 2},
                          {"Tc": 0.008, "Tc_pos_amp": 0.8, "Tc_pos_order": 3}],
    "shaft_compliance": [{"shaft_stiffness": 2.0, "shaft_damping": 2e-4},
                         {"shaft_stiffness": 0.5, "shaft_damping": 1e-4},
                         {"shaft_stiffness": 0.15, "shaft_damping": 5e-5}],
    "backlash": [{"backlash_rad": 0.005}, {"backlash_rad": 0.02}, {"backlash_rad": 0.05}],
    "encoder_quantization": [{"counts_per_rev": 4000}, {"counts_per_rev": 1000},
                             {"counts_per_rev": 500}],
    "inertia_mismatch": [{"_disk": 1.5e-6}, {"_disk": 5e-6}, {"_disk": 1.5e-5}],
}
#: Injected on top of a Coulomb friction (they vary it): found as Coulomb friction
#: first, then the variation.
RIDES_ON = {"direction_friction": "coulomb_friction", "position_friction": "coulomb_friction"}
#: Effects that need a disk on the shaft to exist at all.
DISK_KGM2 = {"shaft_compliance": 1.5e-5, "backlash": 1.5e-5}
#: Damping ratio of the backlash contact (a real keyed disk dissipates at impact; the
#: simulator's default contact has none, an undamped ~400 Hz ringing no rig shows).
CONTACT_ZETA = 0.2


def contact_damping(motor: MotorParams, disk_kgm2: float, zeta: float = CONTACT_ZETA) -> float:
    """N m s/rad across the contact for damping ratio ``zeta`` of the two-mass mode."""
    jr = motor.J * disk_kgm2 / (motor.J + disk_kgm2)
    return float(2.0 * zeta * np.sqrt(motor.contact_stiffness * jr))
LEVELS = ("low", "moderate", "high")
#: testability's amplitude names -> the injection's MotorParams field
AMPLITUDE_KEYS = {"gap_rad": "backlash_rad"}


def clean_motor(seed: int = 0) -> MotorParams:
    """A motor with every unmodelled effect off; Kt and J vary with the seed."""
    rng = np.random.default_rng(1000 + seed)
    return MotorParams(Kt=float(rng.uniform(0.04, 0.07)), J=float(rng.uniform(1e-5, 2.5e-5)),
                       D=float(rng.uniform(1e-6, 4e-6)), Tc=0.0, cog_amp=0.0)


def excitation(kind: str, seed: int = 0, duration_s: float = DURATION_S) -> np.ndarray:
    """Speed command (rad/s): one-way multisine, reversing multisine, slow sweep."""
    t = waveforms.time_base(duration_s)
    rng = np.random.default_rng(seed)
    if kind == "multisine":
        f = np.sort(rng.uniform(0.3, 6.0, 5))
        return waveforms.multisine(t, amplitude=110.0, freqs_hz=f, offset=165.0, seed=seed)
    if kind == "reversing":
        f = np.sort(rng.uniform(0.3, 3.0, 4))
        return waveforms.multisine(t, amplitude=150.0, freqs_hz=f, offset=0.0, seed=seed)
    if kind == BROADBAND:
        return waveforms.chirp(t, amplitude=20.0, f0_hz=1.0, f1_hz=80.0, offset=120.0,
                               method="log")
    if kind == "sweep_slow":
        return waveforms.ramp(t, slope=290.0 / duration_s, offset=10.0)
    raise ValueError(f"unknown excitation {kind!r}")


@dataclass(frozen=True)
class Case:
    effect: str | None          # None = clean control; "a+b" = a composite case
    level: str
    excitation: str
    seed: int
    changes: dict
    #: position unit the diagnoser sees: "rad" (as simulated), "deg" or "m" (a linear
    #: axis behind a 2.5 mm/rev screw) — the same physics in the user's unit
    unit: str = "rad"

    @property
    def effects(self) -> tuple[str, ...]:
        return tuple(self.effect.split("+")) if self.effect else ()


#: Position unit -> factor from radians.
UNITS = {"rad": 1.0, "deg": 180.0 / np.pi, "m": 0.0025 / (2 * np.pi)}
#: What a user states about each unit: the travel per motor revolution (a linear axis's
#: lead), None for angles.
LEAD = {"rad": None, "deg": None, "m": 0.0025}

#: Composite cases: effects injected together (moderate levels), reversing excitation.
COMPOSITES: tuple[tuple[str, ...], ...] = (
    ("coulomb_friction", "current_offset"),
    ("coulomb_friction", "time_delay"),
    ("current_offset", "kt_saturation"),
    ("coulomb_friction", "current_offset", "time_delay"),
    ("coulomb_friction", "time_delay", "kt_saturation"),
)


def composite_case(effects: tuple[str, ...], excitation: str = "reversing", seed: int = 0,
                   unit: str = "rad") -> Case:
    changes: dict = {}
    for e in effects:
        changes.update(INJECTIONS[e][LEVELS.index("moderate")])
    return Case("+".join(effects), "moderate", excitation, seed, changes, unit)


@dataclass(frozen=True)
class Outcome:
    case: Case
    diagnosis: Diagnosis

    @property
    def called(self) -> str | None:
        return self.diagnosis.verdict.effect

    @property
    def isolated(self) -> bool:
        """The verdict names the injected effect — or, for a friction that varies a
        Coulomb term (injected with one), names Coulomb friction with the variation
        named next in the chain (the verdict is the chain's first effect)."""
        base = RIDES_ON.get(self.case.effect or "")
        return self.called == self.case.effect or (
            base is not None and self.called == base and self.case.effect in self.chain)

    @property
    def detected(self) -> bool:
        """Right, or named among the effects this data cannot tell apart."""
        return self.isolated or (self.case.effect is not None and
                                 self.case.effect in self.diagnosis.verdict.confused_with)

    @property
    def chain(self) -> list[str]:
        return [c["effect"] for c in self.diagnosis.chain]

    @property
    def in_chain(self) -> bool:
        """Every injected effect is named somewhere in the chain."""
        return bool(self.case.effects) and all(e in self.chain for e in self.case.effects)

    @property
    def testable(self) -> bool | None:
        """Whether the diagnoser judged, from the trace alone, that it could reveal the
        injected effect (None for clean controls)."""
        for c in self.diagnosis.candidates:
            if c.effect == self.case.effect:
                # below the smallest amplitude the trace can show: not testable either
                small = any(self.case.changes.get(AMPLITUDE_KEYS.get(k, k), np.inf) < v
                            for k, v in (c.min_detectable or {}).items())
                return bool(c.testable and not small)
        return None

    @property
    def true_shrink(self) -> float | None:
        if self.case.effect in RIDES_ON:   # scored only once Coulomb is in: its chain step
            return next((c["shrink_heldout"] for c in self.diagnosis.chain
                         if c["effect"] == self.case.effect), None)
        for c in self.diagnosis.candidates:
            if c.effect == self.case.effect:
                return c.shrink
        return None


def cases(effects=None, levels=LEVELS, excitations=EXCITATIONS, seeds=(0,), clean_seeds=(0, 1, 2)):
    out = []
    for eff in (effects if effects is not None else list(INJECTIONS)):
        for li, lev in enumerate(LEVELS):
            if lev not in levels:
                continue
            for ex in excitations:
                for s in seeds:
                    out.append(Case(eff, lev, ex, s, INJECTIONS[eff][li]))
    for ex in excitations:
        for s in clean_seeds:
            out.append(Case(None, "-", ex, s, {}))
    return out


def blind_trace(case: Case) -> tuple[Trace, GivenModel | None]:
    """Simulate a case; return only what a rig records, plus a given model if any."""
    motor = clean_motor(case.seed)
    changes = dict(case.changes)
    disk = changes.pop("_disk", DISK_KGM2.get(case.effect or "", 0.0))
    if case.effect == "cogging":
        changes["cog_order"] = (6, 10, 8)[case.seed % 3]
    if case.effect == "torque_ripple":
        changes["ripple_order"] = (6, 12, 4)[case.seed % 3]
    motor = replace(motor, **changes)
    if case.effect == "backlash" and not motor.shaft_damping:
        motor = replace(motor, shaft_damping=contact_damping(motor, disk))
    cmd = excitation(case.excitation, case.seed)
    tr = simulate_motor(motor, cmd, mode="velocity", disk_kgm2=disk, seed=case.seed)
    k = UNITS[case.unit]
    blind = Trace(tr.time_s, {"position_rad": np.asarray(tr["position_rad"]) * k,
                              "current_a": tr["current_a"], "command": np.asarray(tr["command"]) * k},
                  {}, source=f"<injected {case.effect or 'clean'} {case.level} {case.excitation}"
                             f" {case.unit}>")
    given = None
    if case.effect == "inertia_mismatch":
        given = GivenModel(motor.Kt / motor.J, motor.D / motor.J, 0.0, "<motor model>")
    return blind, given


def run_case(case: Case, chain: bool = True, state_lead: bool = True) -> Outcome:
    """Diagnose a case blind, stating its position unit (and, for a linear unit, the
    lead unless ``state_lead`` is False) as a user would."""
    trace, given = blind_trace(case)
    lead = LEAD[case.unit] if state_lead else None
    return Outcome(case, diagnose(trace, given, chain=chain, position_unit=case.unit,
                                  travel_per_rev=lead))


# ---------------------------------------------------------------- reducer bench injections
#: Reducer effects injected into the simulated bench (PlantParams changes, moderate).
#: load_losses and speed_losses (churning, ~w^2) have no simulator counterpart (the
#: simulated mesh efficiency is constant or falls with speed; its drag is linear) and are
#: not injected.
BENCH_INJECTIONS = {
    "speed_load_losses": {"cvt": {"eta_max": 0.9, "eta_slope_per_rad_s": 5e-4, "eta_min": 0.3,
                                  "pulsation_amp": 0.0}},
    "ratio_ripple": {"cvt": {"eta_max": 0.9, "eta_slope_per_rad_s": 0.0, "eta_min": 0.9,
                             "pulsation_amp": 0.05, "pulsation_order": 4}},
    "backlash": {"backlash_rad": 0.02},
    "torsional_compliance": {"backlash_rad": 1e-6, "mesh_stiffness": 2.0},
}


def bench_case_trace(effect: str | None, seed: int = 0, duration_s: float = 12.0) -> Trace:
    """A blind bench trace: input speed swept (multisine around 150 rad/s), output
    current oscillating through zero (braking and driving: torque reversals)."""
    from ..sim import CvtParams, MotorParams, PlantParams, simulate_bench

    rng = np.random.default_rng(seed)
    t = np.arange(int(duration_s * 1000)) * 1e-3
    f = rng.uniform(0.2, 0.6, 2)
    cin = 150 + 40 * np.sin(2 * np.pi * f[0] * t) + 20 * np.sin(2 * np.pi * 1.7 * f[0] * t + 1)
    cout = -0.5 + 0.9 * np.sin(2 * np.pi * f[1] * t + rng.uniform(0, 6))
    motor = MotorParams(cog_amp=0.0)
    changes = dict(BENCH_INJECTIONS.get(effect or "", {}))
    if "cvt" in changes:
        changes["cvt"] = CvtParams(**changes["cvt"])
    plant = PlantParams(motor_in=motor, motor_out=motor, seed=seed, **changes)
    tr = simulate_bench(plant, cin, cout, seed=seed)
    return Trace(tr.time_s, {k: tr[k] for k in BENCH_COLUMNS}, {},
                 source=f"<bench {effect or 'clean'} seed {seed}>")
