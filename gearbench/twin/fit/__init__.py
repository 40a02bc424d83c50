"""Fit the simulated bench to a recorded run (output error), with intervals, then add the
effects it lacks one at a time by held-out gain.

Output-error fit: the parameters p of the ``simulation:`` block minimise
S(p) = Σ ((y_measured − y_replay(p))/floor)² over every recorded sample of position,
velocity and current of both motors (``gap.residuals``), the replay being the noise-free
``replay`` of the run's own setpoints. Levenberg–Marquardt (Marquardt 1963) on a
forward-difference Jacobian (steps of 0.5 % of each parameter's scale). The fit runs on
the replay with a 1000x finer encoder and unrounded setpoints (``Problem.smooth``): the
bench's quantisation makes the exact replay piecewise constant in the parameters, and
stalled Gauss-Newton; the gap and the proof use the exact replay.

Intervals (95 %), honest about a coloured residual and an inexact model:

    half-width = 1.96·σ + |b|

* σ² = the largest of three covariances of the least-squares estimate, each
  (JᵀJ)⁻¹ B (JᵀJ)⁻¹: B = s²·JᵀJ (white residual, s² = S/(n − p)), and the block
  sandwich B = Σ_b g_b g_bᵀ (g_b = J_bᵀ r_b) over time blocks of 0.1 s and of
  ``INTERVAL_BLOCK_S`` (heteroscedasticity- and autocorrelation-consistent within a
  block; Newey & West 1987 with a rectangular window). The residual's correlation length
  is not known in advance, and a sandwich over few long blocks underestimates
  (its B has fewer terms than parameters), so no single block length is trusted.
* b = the model-error share: the fit runs on a smoothed replay (``Problem.smooth``) while
  the bench quantises, so the fitted model is not the one that made the data. In the
  effect chain's end (``correct_smoothing_shift``) b is measured: the shift of a refit of
  the smoothed model on the exact replay of the twin, at the fitted values and at
  ``SHIFT_DRAWS`` points drawn around them; the estimate is corrected by −b (their mean),
  their spread joins σ in quadrature (the correction's own uncertainty: the shift at the
  truth is one more draw) and |b| stays in the interval, added linearly, not in quadrature
  (Phillips, Eberhardt & Parry 1997, "Guidelines for expressing the uncertainty of
  measurement results containing uncorrected bias", J. Res. NIST 102(5)). Elsewhere (``fit`` alone)
  b is its first-order estimate b = −(JᵀJ)⁻¹Jᵀ(r_exact − r_smooth) at the fitted values.

Both are carried to the block's SI values by the delta method (J = (J/Kt)·Kt with its
covariance, kt_sat_a = p^(-1/2)). Where the replay is not smooth in the parameters (a
backlash's contact events move by a substep) two more terms enter at the chain's end
(``settle``): σ² gains the replay's own jitter carried to the estimate
(``replay_jitter``), and a fit that stalled on that jitter short of its linearised
minimum either takes that step or has its distance from it added to the interval. Samples
that are not smooth in the parameters at all (a gapped mesh's chatter at its take-up,
chaotic: ``event_mask``) are left out of S for the fit; the profiles still scan S on every
sample.

Effects (the diagnosis vocabulary: ``current_offset``, ``kt_saturation``,
``torque_ripple``, ``stribeck_friction``, ``direction_friction``, ``time_delay``,
``backlash``): each candidate the block has switched off is tried on the current fit:
its parameters are added, one Gauss–Newton step is taken on the even time blocks (the
fit's Jacobian reused, the candidate's columns added), and the step's S on the odd
blocks (held out) is compared with the current model's. Held-out shrink is the fraction
of the held-out S it removes (the floors are estimates, so S − n, the excess over them,
can be negative); the best candidate is added when it is significant (held-out S down
by more than ``MIN_DROP`` floors² and by more than ``MIN_SHRINK`` of itself) and the whole
model is refitted; the chain stops when none is.

Layout: ``params`` (the fitted quantities), ``problem`` (a run to fit, its folds), ``lm`` (the
output-error fit and its intervals), ``smoothness`` (where the replay is not smooth: chatter,
jitter, the smoothing's bias), ``profiles`` (profile intervals), ``effects`` (the effect chain).
"""
from __future__ import annotations

from .params import (AMBIGUOUS_CORR, FD_WEAK, Param, SAT_SCAN, Z95, base_params, candidates,
                     get_value, plain_defaults, replay_key, ripple_cogging_ambiguity, set_value,
                     with_params, written_values)
from .problem import (BLOCK_S, FIT_SIGNALS, ONE_WAY_SHARE, POSITION_SCALE, Problem, REPLAY_CACHE,
                      folds, start_parities, start_values)
from .lm import (FD_REL, INTERVAL_BLOCK_S, MODEL_LIMITED_S_N, REFRESH_GAIN, SECANT_STEPS,
                 STOP_FRACTION, STOP_GAIN, fit, model_limited, set_intervals)
from .smoothness import (EVENT_DRAWS, EVENT_FLOORS, EVENT_PAD_S, JITTER_DRAWS, JITTER_STEP,
                     SHIFT_DRAWS, SHIFT_ITERATIONS, correct_smoothing_shift, event_mask,
                     replay_jitter, settle, smoothing_shift, update_events)
from .profiles import (BASIN_DENSITY, BASIN_SPREAD, CHI2_1_95, PROFILE_STEPS, PROFILE_WIDEN,
                       apply_profiles, carry_profile, profile_interval)
from .effects import (DEBUG, MIN_DROP, MIN_SHRINK, ORDERS_TRIED, PRESCREEN, REFIT_ITERATIONS,
                      SCAN_REFIT, STRONG_DROP, add_effects, angle_free_prefit, backlash_scan,
                      residual_orders, ripple_regressors, scan_start)

__all__ = [
    "AMBIGUOUS_CORR",
    "BASIN_DENSITY",
    "BASIN_SPREAD",
    "BLOCK_S",
    "CHI2_1_95",
    "DEBUG",
    "EVENT_DRAWS",
    "EVENT_FLOORS",
    "EVENT_PAD_S",
    "FD_REL",
    "FD_WEAK",
    "FIT_SIGNALS",
    "INTERVAL_BLOCK_S",
    "JITTER_DRAWS",
    "JITTER_STEP",
    "MIN_DROP",
    "MIN_SHRINK",
    "MODEL_LIMITED_S_N",
    "ONE_WAY_SHARE",
    "ORDERS_TRIED",
    "POSITION_SCALE",
    "PRESCREEN",
    "PROFILE_STEPS",
    "PROFILE_WIDEN",
    "Param",
    "Problem",
    "REFIT_ITERATIONS",
    "REFRESH_GAIN",
    "REPLAY_CACHE",
    "SAT_SCAN",
    "SCAN_REFIT",
    "SECANT_STEPS",
    "SHIFT_DRAWS",
    "SHIFT_ITERATIONS",
    "STOP_FRACTION",
    "STOP_GAIN",
    "STRONG_DROP",
    "Z95",
    "add_effects",
    "angle_free_prefit",
    "apply_profiles",
    "backlash_scan",
    "base_params",
    "candidates",
    "carry_profile",
    "correct_smoothing_shift",
    "event_mask",
    "fit",
    "folds",
    "get_value",
    "model_limited",
    "plain_defaults",
    "profile_interval",
    "replay_jitter",
    "replay_key",
    "residual_orders",
    "ripple_cogging_ambiguity",
    "ripple_regressors",
    "scan_start",
    "set_intervals",
    "set_value",
    "settle",
    "smoothing_shift",
    "start_parities",
    "start_values",
    "update_events",
    "with_params",
    "written_values",
]
