"""Adaptive segments: commands played sample by sample until the estimate is known.

A ``Segment`` with a controller has no fixed command arrays: the sequencer asks the
controller for each sample's setpoints and, every ``CHECK_S`` of bench time, hands it
what was recorded so far. The controller updates its running estimates
(``gearbench.analysis.streaming``: per-block sufficient statistics, never a re-fit of
the whole run) and moves on — to a motor's stop ramp, to the next braking level —
once the statistical 95 % interval meets the profile's target after ``min_s``, or at
``max_s``. What each measurement took, the interval it reached and why it stopped
(``stopped_by: target|max``) are kept in ``measurements`` for result.json.

Targets are on the *statistical* part of an interval, the only part acquisition time
shrinks (docs/profile-format.md, "Adaptive measurement"):
- Kt: ``targets.kt_rel`` is the 95 % half-width of Kt's statistical part, relative;
  the two runs' b2 errors add in variance, so each run stops when its own share
  reaches kt_rel/√2 (eq. 17: a run's relative b2 error moves Kt by J/j unloaded,
  (J + j)/j with the disk). The disk's tolerance and the b2 model term are fixed and
  come on top in the reported Kt interval.
- efficiency: ``targets.eta_pp`` is the 95 % half-width of the staircase slope's
  statistical part (eq. 18 as a slope), in percentage points; each level stops when
  its settled mean's standard error is what the slope needs (``slope_target_sem``),
  the error computed as the final analysis computes it (block means,
  ``streaming.tapered_mean_sem``, with its t quantile). Levels are judged on the input
  current less its rotor's inertial part where that is the quieter series
  (``efficiency.inertia_corrected_current``: no waiting for a slow speed loop's
  recovery), count as settled only with the input speed back at its command, and may
  use what earlier levels of the staircase left of their max_s (issue 23).
"""
from __future__ import annotations

import math

import numpy as np

from ..analysis.uncertainty import coverage_factor
from ..analysis.efficiency import SPEED_SPAN_S, inertia_corrected_current
from ..analysis.streaming import MIN_SETTLED_CHUNKS, SETTLE_MARGIN, LevelMean, StreamingB2, Z95, slope_fit, slope_target_sem, window_stats

CORRECTED_MARGIN = 1.0      # inertia-corrected levels: the window starts where found steady
CHECK_S = 0.1                # calibration: how often the running b2 estimates are updated
LEVEL_CHUNK_S = 0.02         # efficiency: chunk of the level means (below the ripple periods' tens)


def stop_ramp(speed: float, ramp_rad_s2: float, period_s: float) -> np.ndarray:
    """Speed command from ``speed`` down to rest at ``ramp_rad_s2`` (at least 50 ms): every
    segment ends with the motor stopped."""
    n = int(round(max(abs(speed) / ramp_rad_s2, 0.05) / period_s))
    return np.linspace(speed, 0.0, n + 1)[1:]


class CalibrationRuns:
    """One or more motors each playing its calibration waveform at once (one run of each:
    unloaded or with its disk); each motor stops — stop ramp, then 0 — on its own."""

    def __init__(self, runs: dict, *, period_s: float, min_s: float, max_s: float, kt_rel: float,
                 ramp_rad_s2: float, segment: str):
        # runs: motor -> dict(command=array (max length), velocity=bool, share=callable(b2) -> float,
        #                     label=str)
        self.runs = runs
        self.period_s = period_s
        self.min_n = int(round(min_s / period_s))
        self.max_n = int(round(max_s / period_s))
        self.target = kt_rel / math.sqrt(2.0)       # each of the two runs' share of kt_rel
        self.segment = segment
        self.check_every = max(1, int(round(CHECK_S / period_s)))
        self.fits = {m: StreamingB2(period_s) for m in runs}
        self.stop_at: dict[str, int] = {}
        self.stopped_by: dict[str, str] = {}
        self.reached: dict[str, float] = {}
        self.b2: dict[str, float] = {}
        self.tails: dict[str, np.ndarray] = {}
        for m, r in runs.items():
            r["command"] = np.asarray(r["command"], float)[: self.max_n]
        ramp_max = max(len(stop_ramp(float(np.max(np.abs(r["command"]))), ramp_rad_s2, period_s))
                       if r["velocity"] else 0 for r in runs.values())
        self.ramp_rad_s2 = ramp_rad_s2
        self.max_samples = self.max_n + ramp_max

    def _stop(self, m: str, k: int, why: str) -> None:
        r = self.runs[m]
        self.stop_at[m] = k
        self.stopped_by[m] = why
        last = float(r["command"][k - 1]) if k > 0 else 0.0
        self.tails[m] = stop_ramp(last, self.ramp_rad_s2, self.period_s) if r["velocity"] else np.zeros(0)

    def setpoints(self, k: int) -> dict[str, float]:
        out = {}
        for m, r in self.runs.items():
            s = self.stop_at.get(m)
            if s is None and k >= self.max_n:
                self._estimate(m)
                self._stop(m, self.max_n, "max" if self.target > 0 else "duration")
                s = self.max_n
            if s is None:
                out[m] = float(r["command"][k])
            else:
                tail = self.tails[m]
                out[m] = float(tail[k - s]) if k - s < len(tail) else 0.0
        return out

    def _estimate(self, m: str) -> None:
        est = self.fits[m].estimate()
        if est is None:
            return
        b2, sd, dof = est
        self.b2[m] = b2
        share = self.runs[m]["share"](b2)
        self.reached[m] = share * coverage_factor(dof) * sd / abs(b2) if b2 else math.inf

    def update(self, k: int, cols: dict) -> bool:
        """Called with ``k`` samples recorded; returns True when the segment is over."""
        if k % self.check_every == 0:
            for m in self.runs:
                if m in self.stop_at:
                    continue
                self.fits[m].update(cols[f"{m}.position_rad"], cols[f"{m}.current_a"], k)
                self._estimate(m)
                if k >= self.min_n and self.reached.get(m, math.inf) <= self.target:
                    self._stop(m, k, "target")
        return len(self.stop_at) == len(self.runs) and all(
            k >= s + len(self.tails[m]) for m, s in self.stop_at.items())

    def end_sample(self, m: str) -> int:
        """Samples of motor ``m``'s run including its stop ramp (its trace for the analysis)."""
        return self.stop_at[m] + len(self.tails[m])

    def measurements(self) -> list[dict]:
        return [{"name": f"{self.segment}:{m}", "kind": "calibrate", "segment": self.segment,
                 "motor": m, "run": self.runs[m]["label"],
                 "duration_s": self.stop_at[m] * self.period_s,
                 "quantity": "Kt statistical 95 % half-width (relative), this run's share",
                 "interval_reached": self.reached.get(m), "target": self.target,
                 "b2_streaming": self.b2.get(m), "stopped_by": self.stopped_by[m],
                 "run_samples": self.end_sample(m)}
                for m in self.runs if m in self.stop_at]


class Staircase:
    """One input speed: ramp up, zero-load level, each braking level (output current),
    then the braking released and the stop ramp. Each level lasts until it has settled
    and its mean is known as well as the slope needs (or ``max_s``)."""

    def __init__(self, *, speed: float, currents_out_a: list[float], torques_out_nm: list[float],
                 period_s: float, min_s: float, max_s: float, eta_pp: float, kt_in: float,
                 kt_out: float, eta_prior: float, ratio_prior: float | None, ramp_rad_s2: float,
                 segment: str, settle_floor_chunks: int = 0, loss_out=None, inertia_kgm2: dict | None = None):
        self.speed = speed
        # with both rotors' J calibrated, levels are judged on the currents less each rotor's
        # inertial part (efficiency.inertia_corrected_current, as the final analysis then
        # takes them): the speed loop's recovery after a braking step no longer has to die
        # out in the current before a level counts as settled
        self.inertia = dict(inertia_kgm2 or {})
        self.corrected = all(self.inertia.get(m, 0) > 0 for m in ("in", "out"))
        # samples a corrected current waits for (the speed averaged over SPEED_SPAN_S after it)
        self.lag = int(round(SPEED_SPAN_S / 2 / period_s)) + 1 if self.corrected else 0
        self.levels = [0.0] + list(currents_out_a)
        # the output motor's own friction (D, Tc from its calibration) brakes the reducer too:
        # once the zero-load level shows the output speed, each braking current is lowered by
        # it, so the shaft carries the profile's torque on every station, whatever its motor
        self.loss_out = loss_out
        self.compensated_nm: float | None = None
        self.torques = [0.0] + list(torques_out_nm)
        self.period_s = period_s
        self.min_n = int(round(min_s / period_s))
        self.max_n = int(round(max_s / period_s))
        self.eta_pp = eta_pp
        self.kt_in, self.kt_out = kt_in, kt_out
        self.eta_prior, self.ratio_prior = eta_prior, ratio_prior
        self.segment = segment
        self.chunk = max(1, int(round(LEVEL_CHUNK_S / period_s)))
        self.n_ramp = int(round(max(abs(speed) / ramp_rad_s2, 0.05) / period_s))
        self.up = np.linspace(0.0, speed, self.n_ramp)
        self.down = stop_ramp(speed, ramp_rad_s2, period_s)
        self.max_samples = self.n_ramp + len(self.levels) * self.max_n + len(self.down)
        self.level = -1              # -1: ramping up; len(levels): stopping
        self.level_start = self.n_ramp
        self.stop_start: int | None = None
        self.settle_floor = settle_floor_chunks   # chunks: slowest settling of a braking step so far
        self.acc = self._level_mean(CORRECTED_MARGIN if self.corrected else SETTLE_MARGIN)
        self.acc_raw = self._level_mean(SETTLE_MARGIN) if self.corrected else None
        self.done_levels: list[dict] = []
        self._cols: dict | None = None

    def _level_max(self) -> int:
        """Samples the current level may take: its max_s plus what the levels before it in
        this staircase left unused (the staircase never exceeds its levels' max_s summed,
        the profile's bench-time bound; the time goes where the slope still needs it).
        Not a share by leverage up front: the cvt's first zero-load level then took up to
        1.4 s where it met its target in less (--sim bench 16.0 -> 17.4 s) for one plant
        in eighty more within the bound."""
        used = sum(r["stop"] - r["start"] for r in self.done_levels)
        return self.max_n * (len(self.done_levels) + 1) - used

    def _level_mean(self, margin: float) -> LevelMean:
        return LevelMean(self.settle_floor, margin=margin, speed_rad_s=self.speed, dt_s=self.period_s)

    def _currents(self, cols: dict, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        """Input and output currents of samples a..b-1 as the analysis takes them (inertia
        corrected when the rotors' J are known; needs the angle at sample b)."""
        if not self.corrected:
            return cols["in.current_a"][a:b], cols["out.current_a"][a:b]
        out = [cols["out.current_a"][a:b]]        # the output motor as measured (efficiency())
        pad = self.lag + 1
        for m, kt in (("in", self.kt_in),):
            lo = max(a - pad, 0)
            cur = inertia_corrected_current(cols[f"{m}.current_a"][lo:b + pad], cols[f"{m}.position_rad"][lo:b + pad],
                                            self.period_s, self.inertia[m], kt)
            out.insert(0, cur[a - lo:a - lo + (b - a)])
        return out[0], out[1]

    # -- commands
    def setpoints(self, k: int) -> dict[str, float]:
        if k < self.n_ramp:
            return {"in": float(self.up[k]), "out": 0.0}
        if self.level < 0:
            self.level = 0
        if self.stop_start is None and self.level < len(self.levels) and k - self.level_start >= self._level_max():
            self._next(k, "max", self._cols)
        if self.stop_start is not None:
            j = k - self.stop_start
            return {"in": float(self.down[j]) if j < len(self.down) else 0.0, "out": 0.0}
        return {"in": self.speed, "out": self.levels[self.level]}

    # -- estimates
    def _slope_now(self, extra: dict | None = None):
        """(slope, η) from the levels done (plus the current one), or the prior."""
        pts = [r for r in self.done_levels + ([extra] if extra else []) if "mean_in" in r]
        n = self._ratio(pts)
        if len(pts) >= 2:
            _, b, _ = slope_fit([p["mean_out"] for p in pts], [p["mean_in"] for p in pts],
                                [p["sem_in"] for p in pts], [p["sem_out"] for p in pts])
            if np.isfinite(b) and b != 0:
                eta = -self.kt_out / (n * self.kt_in * b)
                if 0.02 < eta <= 1.5:
                    return b, eta
        eta = self.eta_prior
        return -self.kt_out / (n * self.kt_in * eta), eta

    def _ratio(self, pts) -> float:
        din = sum(p.get("dth_in", 0.0) for p in pts)
        dout = sum(p.get("dth_out", 0.0) for p in pts)
        if abs(dout) > 0 and abs(din) > 0:
            return din / dout
        return self.ratio_prior or 1.0

    def _level_record(self, k: int, cols: dict, why: str | None, st: dict | None) -> dict:
        settle_n = (st["settle_chunk"] * self.chunk) if st else (k - self.level_start)
        a = self.level_start + settle_n
        pos_in, pos_out = cols["in.position_rad"], cols["out.position_rad"]
        rec = {"level": self.level, "start": self.level_start, "settled": a, "stop": k,
               "torque_out_nm": self.torques[self.level], "out_command": self.levels[self.level],
               "dth_in": float(pos_in[k - 1] - pos_in[a]) if k - 1 > a else 0.0,
               "dth_out": float(pos_out[k - 1] - pos_out[a]) if k - 1 > a else 0.0}
        if st:
            rec.update({q: st[q] for q in ("mean_in", "mean_out", "sem_in", "sem_out")})
        return rec

    def update(self, k: int, cols: dict) -> bool:
        self._cols = cols          # the recorder's buffers: a level ending at max_s reads them
        if self.stop_start is not None:
            return k >= self.stop_start + len(self.down)
        # a corrected current needs the angles after it: chunks lag by self.lag + 1 samples,
        # aligned on the level's start as the windows are
        b = k - self.lag - 1
        if k <= self.n_ramp or b <= self.level_start or (b - self.level_start) % self.chunk:
            return False
        a = b - self.chunk
        travel = float(cols["in.position_rad"][b] - cols["in.position_rad"][a])
        self.acc.add_chunk(*self._currents(cols, a, b), travel)
        st = self.acc.stats()
        if self.acc_raw is not None:                 # the zero-load level: both series
            self.acc_raw.add_chunk(cols["in.current_a"][a:b], cols["out.current_a"][a:b], travel)
            st = _quieter(st, self.acc_raw.stats())
        if st is None or k - self.level_start < self.min_n:
            return False
        rec = self._level_record(k, cols, None, st)
        b, eta = self._slope_now(rec)
        need = slope_target_sem(self.eta_pp, eta, b, self._x_levels(), self.level)
        # the final interval is t(dof) wide on block-means errors, not 1.96
        have = math.hypot(st["sem_in"], b * st["sem_out"]) * coverage_factor(st["dof"]) / Z95
        if have <= need and st["steady"]:
            self._next(k, "target", cols, st)
        return False

    def _x_levels(self) -> np.ndarray:
        return np.array(self.levels)

    def _next(self, k: int, why: str, cols: dict | None = None, st: dict | None = None) -> None:
        """Close the current level at sample ``k``; start the next one or the stop."""
        if self.acc_raw is not None:
            # the zero-load level decides the staircase's series: the corrected current where
            # its mean is known better (a slow speed loop still recovering), else as measured
            # (a shaft ripple the rotor's inertia passes on makes the correction noisier)
            st_c, st_r = self.acc.stats(), self.acc_raw.stats()
            if _quieter(st_c, st_r) is st_r and st_r is not None:
                self.corrected, self.lag, self.acc, st = False, 0, self.acc_raw, st_r
            else:
                st = st_c
            self.acc_raw = None
        if st is None:
            st = self.acc.stats()
        if st is None and cols is not None:       # never settled within max_s: its last half
            st = {"settle_chunk": 0, **window_stats(*self._currents(cols, self.level_start + (k - self.level_start) // 2,
                                                                        k - self.lag - 1))}
            st["settle_chunk"] = (k - self.level_start) // 2 // self.chunk
            st["unsettled"] = True
        rec = self._level_record(k, cols, why, st) if cols is not None else {
            "level": self.level, "start": self.level_start, "stop": k, "pending": True,
            "torque_out_nm": self.torques[self.level], "out_command": self.levels[self.level]}
        rec["stopped_by"] = why
        if st is not None and st.get("unsettled"):
            rec["settled_in_time"] = False
        rec["floor"] = self.acc._settled_at if not self.acc.n else min(self.acc._settled_at, len(self.acc.n))
        rec["duration_s"] = (k - self.level_start) * self.period_s
        if st is not None:
            b, eta = self._slope_now(rec if "mean_in" in rec else None)
            rec["settle_s"] = st["settle_chunk"] * self.chunk * self.period_s
            # the slope's half-width if every level had its share of the error like this one
            need = slope_target_sem(self.eta_pp, eta, b, self._x_levels(), self.level)
            have = math.hypot(st["sem_in"], b * st["sem_out"]) * coverage_factor(st.get("dof", 1e9)) / Z95
            rec["interval_reached"] = self.eta_pp * have / need if need > 0 else math.inf
        self.done_levels.append(rec)
        if self.level == 0:
            self._compensate_friction(rec)
        if self.level >= 1:
            # a braking step settles no faster than the slowest one before it on this drive
            # (the point found steady, not the window start: that doubles it once per level)
            # (a level that never settled raises it only as far as still lets the next one
            # settle within max_s: the whole level as the floor left every later one unsettled)
            cap = (self.max_n // self.chunk - MIN_SETTLED_CHUNKS) // SETTLE_MARGIN
            self.settle_floor = max(self.settle_floor, min(cap, st.get("steady_chunk", st["settle_chunk"])
                                    if st is not None and not st.get("unsettled")
                                    else (k - self.level_start) // self.chunk))
        self.level += 1
        self.level_start = k
        # a corrected current carries no speed-loop tail to let decay further
        self.acc = self._level_mean(CORRECTED_MARGIN if self.corrected else SETTLE_MARGIN)
        if self.level >= len(self.levels):
            self.stop_start = k

    def _compensate_friction(self, zero_load: dict) -> None:
        span = (zero_load.get("stop", 0) - zero_load.get("settled", zero_load.get("stop", 0))) * self.period_s
        if self.loss_out is None or span <= 0 or not zero_load.get("dth_out"):
            return
        loss = abs(self.loss_out(zero_load["dth_out"] / span))
        # a motor whose own friction brakes more than half what the lightest level asks:
        # compensated, that level would brake with next to no current (random plant 3/3: 0.01 A
        # left, its input-current rise within the noise, the analysis refused it) or the
        # levels would merge at zero (no slope); its points then carry t + loss
        if not np.isfinite(loss) or loss >= 0.5 * min((abs(t) for t in self.torques[1:] if t), default=0.0):
            return
        self.compensated_nm = loss
        self.levels[1:] = [-max(abs(t) - loss, 0.0) / self.kt_out for t in self.torques[1:]]

    def finish(self, cols: dict, n: int) -> None:
        """Fill in levels that ended at ``max_s`` inside ``setpoints`` (no columns there)."""
        for rec in self.done_levels:
            if rec.pop("pending", False):
                acc = LevelMean(rec.get("floor", 0), margin=CORRECTED_MARGIN if self.corrected else SETTLE_MARGIN,
                                speed_rad_s=self.speed, dt_s=self.period_s)
                for a in range(rec["start"], rec["stop"] - self.chunk, self.chunk):
                    acc.add_chunk(*self._currents(cols, a, a + self.chunk),
                                  float(cols["in.position_rad"][a + self.chunk] - cols["in.position_rad"][a]))
                st = acc.stats()
                # never settled within max_s: the level's last half, the least disturbed part
                # (its standard error from the whole level's chunks; flagged in result.json)
                settle_n = st["settle_chunk"] * self.chunk if st else (rec["stop"] - rec["start"]) // 2
                a = rec["start"] + settle_n
                k = rec["stop"]
                if st is None:
                    st = {"settle_chunk": 0, **window_stats(*self._currents(cols, a, k - self.lag - 1))}
                    rec["settled_in_time"] = False
                rec.update(settled=a, settle_s=settle_n * self.period_s,
                           dth_in=float(cols["in.position_rad"][k - 1] - cols["in.position_rad"][a]),
                           dth_out=float(cols["out.position_rad"][k - 1] - cols["out.position_rad"][a]))
                if st:
                    rec.update({q: st[q] for q in ("mean_in", "mean_out", "sem_in", "sem_out")})
        # the slope's running 95 % half-width over all levels, as the stopping rule saw it
        pts = [r for r in self.done_levels if "mean_in" in r]
        self.slope_half_width_pp = None
        if len(pts) >= 2:
            _, b, sb = slope_fit([p["mean_out"] for p in pts], [p["mean_in"] for p in pts],
                                 [p["sem_in"] for p in pts], [p["sem_out"] for p in pts])
            n = self._ratio(pts)
            eta = -self.kt_out / (n * self.kt_in * b) if b else float("nan")
            self.slope_half_width_pp = 100 * Z95 * abs(eta) * sb / abs(b) if b else None

    def windows(self, counter: np.ndarray) -> list[tuple[int, int]]:
        """Settled part of each level as sample-counter values [first, last)."""
        out = []
        for r in self.done_levels:
            # the corrected current's last samples use angles from the next level's start
            a, b = r.get("settled", r["start"]), r["stop"] - self.lag - 1 if self.lag else r["stop"]
            if b - a >= 2:
                out.append((int(counter[a]), int(counter[b - 1]) + 1))
                r["window_samples"] = list(out[-1])
        return out

    def measurements(self) -> list[dict]:
        return [{"name": f"{self.segment}:{r['torque_out_nm']:g}Nm", "kind": "efficiency",
                 "segment": self.segment, "speed_in_rad_s": self.speed,
                 "torque_out_nm": r["torque_out_nm"], "reference": r["torque_out_nm"] == 0,
                 "duration_s": r["duration_s"], "settle_s": r.get("settle_s"),
                 "quantity": "incremental efficiency slope 95 % statistical half-width (pp) if "
                             "every level met its share as this one did (shares by leverage)",
                 "interval_reached": r.get("interval_reached"), "target": self.eta_pp,
                 "settled_in_time": r.get("settled_in_time", True),
                 "window_samples": r.get("window_samples"),
                 "out_command_a": r.get("out_command"),
                 "friction_compensated_nm": self.compensated_nm if r["torque_out_nm"] else None,
                 "inertia_corrected": self.corrected,
                 "stopped_by": r["stopped_by"]} for r in self.done_levels]


def _quieter(a: dict | None, b: dict | None) -> dict | None:
    """Of two level statistics (either None while unsettled), the one whose input-current
    mean has the smaller standard error."""
    if a is None or b is None:
        return a if b is None else b
    return b if b["sem_in"] < a["sem_in"] else a
