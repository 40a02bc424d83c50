"""A recorded run to fit (``Problem``): its segments, noise floors, the replay cache, and the
held-out time folds."""
from __future__ import annotations

import copy
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from ...errors import ProfileError
from ...sim import PlantParams
from ..gap import noise_floors, residuals
from ..replay import AXES, Quanta, Segment, replay
from .params import Param, _basin_values, get_value, replay_key, set_value


BLOCK_S = 0.1          # time block of the held-out folds
ONE_WAY_SHARE = 0.02  # a motor turning the other way for less than this share of its moving samples turns one way
# replays kept per fit (``Problem.residual_vector``): a fit replays the same parameter vector
# again and again (an effect screened at "off" is the current fit; a profile's centre and the
# intervals' exact replay are the fit's; the refit-screened candidates' base); 3 MB each on a
# cyclo run
REPLAY_CACHE = 48
FIT_SIGNALS = ("position_rad", "velocity_rad_s", "current_a")
# position counts in S with its floor times POSITION_SCALE: a model error accumulates in
# the angle over a whole step (a ratio 0.03 % off moves the output angle by hundreds of
# encoder counts), so at its bare floor (a third of a count) it drowns the currents that
# carry Kt, friction and η; without it, the ratio and η were confounded through the input
# current (T_out/(n·η)) and a hidden cvt run's ratio came out 8.155 for 8.100, which the
# angles alone rule out (S of the output angle ×10⁵ at 8.13)
POSITION_SCALE = 30.0


@dataclass
class Problem:
    """A run to fit: its segments, floors, the drives' quanta and the starting block."""

    segments: list[Segment]
    block: dict
    quanta: Quanta = field(default_factory=Quanta)
    floors: dict = field(default_factory=dict)
    evaluations: int = 0
    smooth: bool = True     # fit on the unquantised replay (``residual_vector``)
    # signals in S: a torque-mode run replayed open loop (EMPS) drifts in angle, so its
    # angle is left out and only its velocity is fitted
    signals: tuple = FIT_SIGNALS
    # data replaced by a replay: subtracted from every residual (``retargeted``)
    target: np.ndarray | None = None
    # stacked residuals left out of S (zeroed; ``event_mask``): None keeps every sample
    events: np.ndarray | None = None

    def __post_init__(self):
        if not self.floors:
            self.floors = noise_floors(self.segments)
        # per (axis, signal) a factor on the floor: each signal weighs 1/(floor·scale)² in S
        # (POSITION_SCALE for the angles, 1 for the rest)
        self.scales = {k: (POSITION_SCALE if k[1] == "position_rad" else 1.0) for k in self.floors}
        # time blocks of BLOCK_S for the sandwich and the folds, in residual order
        self._blocks = None
        self._where = None      # (step, sample) of each stacked residual (``sample_index``)
        self.profiles = []      # ``apply_profiles``' results of the last chain
        self.ambiguities = []   # effects the run cannot tell apart (``ripple_cogging_ambiguity``)
        # (smooth, plant) -> residual; shared with the chain's sub-problems (``share_cache``)
        self._cache: OrderedDict = OrderedDict()
        self.cache_hits = 0

    def share_cache(self, other: "Problem") -> "Problem":
        """Use ``other``'s replay cache (the same run and floors), its blocks and the samples
        it leaves out; returns self."""
        self._cache, self._blocks, self.events = other._cache, other._blocks, other.events
        return self

    def plant(self, block: dict) -> PlantParams:
        return PlantParams.from_dict(block, "simulation")

    def retargeted(self, r_data: np.ndarray) -> "Problem":
        """The same run with its data replaced by the replay whose residual is ``r_data``:
        the residual is linear in the data, so (y_meas − y(p))/floor − r_data =
        (y_replay − y(p))/floor. Shares the replay cache (it holds the untargeted residuals)."""
        other = copy.copy(self)
        other.target = np.asarray(r_data, float)
        return other

    def residual_vector(self, block: dict, smooth: bool | None = None,
                        every_sample: bool = False) -> np.ndarray | None:
        """Stacked residuals in floors (None when the block is not a valid plant), zero on
        the samples ``events`` leaves out unless ``every_sample``.

        ``smooth``: the encoder 1000x finer, the current unrounded and setpoints unrounded:
        the quantised replay is piecewise constant in the parameters (a 0.5 % step of Kt
        moves the noise-free current by less than its 1 mA resolution), which gave the
        forward differences zeros and jumps and stalled Gauss-Newton far from the optimum."""
        smooth = self.smooth if smooth is None else smooth
        try:
            if smooth:
                block = copy.deepcopy(block)
                for a in AXES:
                    cpr = get_value(block, f"motors.{a}.counts_per_rev")
                    set_value(block, f"motors.{a}.counts_per_rev", int(cpr) * 1000)
                    set_value(block, f"motors.{a}.current_resolution_a", 0.0)
            plant = self.plant(block)
        except ProfileError:
            return None
        key = (smooth, replay_key(plant))
        if key in self._cache:
            self._cache.move_to_end(key)
            self.cache_hits += 1
            return self._kept(self._targeted(self._cache[key]), every_sample)
        self.evaluations += 1
        try:
            rows = replay(plant, self.segments, quanta=Quanta() if smooth else self.quanta)
        except ProfileError:     # a step into a plant the world cannot run (too stiff a mesh)
            return None
        res = residuals(rows, self.segments, self.weighted_floors())
        r = np.concatenate([res[k] for k in sorted(res) if k[2] in self.signals])
        r = r if np.all(np.isfinite(r)) else None
        if r is not None:
            r.flags.writeable = False     # shared by every caller of the same vector
        self._cache[key] = r
        while len(self._cache) > REPLAY_CACHE:
            self._cache.popitem(last=False)
        return self._kept(self._targeted(r), every_sample)

    def _targeted(self, r: np.ndarray | None) -> np.ndarray | None:
        return r if r is None or self.target is None else r - self.target

    def _kept(self, r: np.ndarray | None, every_sample: bool) -> np.ndarray | None:
        if r is None or every_sample or self.events is None or not self.events.any():
            return r
        r = r.copy()
        r[self.events] = 0.0
        return r

    def sample_index(self) -> tuple[np.ndarray, np.ndarray]:
        """(step index, sample index within the step) of every stacked residual."""
        if self._where is None:
            segidx = {s.name: i for i, s in enumerate(self.segments)}
            segs = {s.name: s for s in self.segments}
            steps, samples = [], []
            for k in self.residual_keys():
                n = segs[k[0]].last_sample - segs[k[0]].first_sample + 1
                steps.append(np.full(n, segidx[k[0]], np.int64))
                samples.append(np.arange(n, dtype=np.int64))
            self._where = (np.concatenate(steps), np.concatenate(samples))
        return self._where

    def peak_currents(self) -> dict:
        """Per axis the largest |current| the run recorded (A)."""
        out = {}
        for a in AXES:
            v = [float(np.max(np.abs(np.asarray(s.trace[f"{a}.current_a"], float))))
                 for s in self.segments if f"{a}.current_a" in s.trace and len(s.trace)]
            out[a] = max(v, default=0.0)
        return out

    def turning(self) -> dict:
        """Per axis "both", "forward", "backward" or "still": which ways the run turns the
        motor. One way = turning the other way for less than ``ONE_WAY_SHARE`` of its moving
        samples (|ω| above 1 % of its largest). On such a motor a direction-dependent
        Coulomb friction is one number, Tc ± Tc_asym: not identifiable from the run."""
        out = {}
        for a in AXES:
            v = np.concatenate([np.asarray(s.trace[f"{a}.velocity_rad_s"], float) for s in self.segments
                                if f"{a}.velocity_rad_s" in s.trace] or [np.zeros(0)])
            top = float(np.max(np.abs(v), initial=0.0))
            fwd, back = int((v > 0.01 * top).sum()), int((v < -0.01 * top).sum())
            if top == 0.0 or fwd + back == 0:
                out[a] = "still"
            elif min(fwd, back) >= ONE_WAY_SHARE * (fwd + back):
                out[a] = "both"
            else:
                out[a] = "forward" if fwd > back else "backward"
        return out

    def not_identifiable(self) -> list[str]:
        """What this run cannot show (said beside the fitted block, not fitted)."""
        return ([f"direction-dependent friction of motor {a}: the run turns it {way} only, so its "
                 f"fitted Tc is the {way} Coulomb friction; a profile that reverses motor {a} is "
                 f"predicted with it (record a reversing step to fit motors.{a}.Tc_asym)"
                 for a, way in self.turning().items() if way in ("forward", "backward")]
                + [f"{pr['path']}: S is as low at {_basin_values(pr)} as at its profile's minimum "
                   f"{pr['written']:.4g} (within the 95 % rise): its size is not resolved by this "
                   f"run; its interval and those of the parameters that follow it reach there"
                   for pr in self.profiles if pr.get("basins")])

    def ratio_resolution(self) -> float:
        """The ratio's resolution from the angles (relative): one output encoder count over
        the output's whole travel in the coupled steps. The angles at the ends of a step are
        known to a count whatever the averaging; a block sandwich of 0.5 s cannot see an
        error that lasts a whole step (a hidden cyclo run: ±0.00007 % from the covariances,
        ±0.0002 % from this)."""
        travel, q = 0.0, float("inf")
        for s in self.segments:
            if s.coupling != "reducer" or "out.position_rad" not in s.trace:
                continue
            th = np.asarray(s.trace["out.position_rad"], float)
            travel += float(np.sum(np.abs(np.diff(th))))
            d = np.abs(np.diff(th))
            d = d[d > 1e-12]
            if d.size:
                q = min(q, float(d.min()))
        return q / travel if travel > 0 and q < float("inf") else 0.0

    def residual_keys(self) -> list[tuple]:
        """(step, axis, signal) of each part of the stacked residual, in its order."""
        if getattr(self, "_keys", None) is None:
            res = residuals({s.name: np.zeros((s.last_sample - s.first_sample + 1, 16))
                             for s in self.segments}, self.segments, self.floors)
            self._keys = [k for k in sorted(res) if k[2] in self.signals]
        return self._keys

    def signal_mask(self, exclude: tuple = ()) -> np.ndarray:
        """True on every stacked residual (``residual_vector``'s order) whose signal is not
        in ``exclude``."""
        segs = {s.name: s for s in self.segments}
        return np.concatenate([np.full(segs[k[0]].last_sample - segs[k[0]].first_sample + 1, k[2] not in exclude)
                               for k in self.residual_keys()])

    def weighted_floors(self) -> dict:
        return {k: v * self.scales.get(k, 1.0) for k, v in self.floors.items()}

    def blocks(self, span_s: float = BLOCK_S) -> np.ndarray:
        """Time-block id of every stacked residual (same order as ``residual_vector``)."""
        if span_s != BLOCK_S:
            base = self.blocks()
            t = (base % 100000) * BLOCK_S
            return (base // 100000) * 100000 + (t // span_s + 1e-9).astype(np.int64)
        if self._blocks is None:
            res = residuals({s.name: np.zeros((s.last_sample - s.first_sample + 1, 16))
                             for s in self.segments}, self.segments, self.floors)
            ids = []
            segidx = {s.name: i for i, s in enumerate(self.segments)}
            for key in sorted(res):
                if key[2] not in self.signals:
                    continue
                seg = self.segments[segidx[key[0]]]
                t = seg.trace.time_s - seg.trace.time_s[0]
                ids.append(segidx[key[0]] * 100000 + (t // BLOCK_S).astype(np.int64))
            self._blocks = np.concatenate(ids)
        return self._blocks


def folds(prob: Problem) -> tuple[np.ndarray, np.ndarray]:
    """Alternate time blocks: the fit fold and the held-out fold. Each step's first block
    holds its start (the motors leave zero speed): with one parity in every step all
    starts were in the fit fold, and an effect that shows there (a Stribeck friction)
    gained 9,400 floors² on the fit fold and 78 on the held-out one and was never added
    (cvt random seed 108). So each step's parity is chosen, in order, to put its start in
    the fold that has held fewer starts of the motors it moves (``start_parities``)."""
    b = prob.blocks()
    par = start_parities(prob)
    even = (b % 100000 + par[b // 100000]) % 2 == 0
    return even, ~even


def start_parities(prob: Problem) -> np.ndarray:
    """Per step 0 or 1: the fold its first block goes to, balancing each motor's starts
    between the folds (a motor moves in a step when its drive is not off)."""
    starts = {a: [0, 0] for a in AXES}
    out = []
    for s in prob.segments:
        moving = [a for a in AXES if s.modes.get(a, "off") != "off"]
        k = min((0, 1), key=lambda f: (sum(starts[a][f] for a in moving), f))
        for a in moving:
            starts[a][k] += 1
        out.append(k)
    return np.array(out, np.int64)


def start_values(prob: Problem, params: list[Param]) -> np.ndarray:
    """The params' values in the starting block (the profile's), in fitted units."""
    out = []
    for p in params:
        v = get_value(prob.block, p.path)
        if v is None:
            out.append(p.value)
        elif p.transform.startswith("per_kt:"):
            out.append(float(v) / float(get_value(prob.block, f"motors.{p.transform[7:]}.Kt")))
        elif p.transform == "invsq":
            out.append(1.0 / float(v) ** 2 if v else 0.0)
        else:
            out.append(float(v))
    return np.array(out, float)
