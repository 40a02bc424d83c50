"""Single-run motor identification: ``J θ'' + D θ' + Tc s(θ') + C θ = Kt i``.

Two methods, same result type:

``paper``   Yukawa et al., eqs. 6–10: state x = [θ, θ'], input u = i, forward (Euler)
            differences at the data's rate, equation-error least squares written with
            the Q matrices (integrals as sums × dt). Returns A_e, B_e; b2 = B_e[1] = Kt/J.
            ``decimate_s=0.015`` reproduces the paper's 15 ms sampling (every k-th
            sample, as a 15 ms A/D would see it).
``default`` Removes the paper's biases: one zero-phase FIR on every signal and central
            differences (see ``derivatives.consistent_derivatives``) so velocity,
            acceleration and current stay aligned; a Coulomb term sign(θ') instead
            of subtracting a no-load current, integrated at each reversal's
            sub-sample instant as the angle's second difference sees it; stuck and
            breakaway stretches (a dwell the drive pushes against) left out of the
            equation (``equation_weight``: the raw equation is weighted 0 there before
            the filter, so the fit stays exact on what remains and its intervals count
            only that; a rotor at rest that nothing pushes stays in, friction 0 there);
            C fixed at 0 unless asked; a
            current-noise (errors-in-variables) correction; cogging harmonics
            sin/cos(k θ) with the orders k found from the data (``cogging_order_scores``
            screens k = 1…64 on the rotor angle, an information criterion keeps them);
            a parameter covariance from overlapping window sums of the residual scores
            (a Bartlett HAC estimate, valid for coloured residuals; window = the FIR or
            8 correlation times of the residual) with Student-t degrees of freedom
            1.5 (n/window − 1); optionally the setpoint-step term of a drive that steps
            its speed setpoint every SYNC (``setpoint_step``, shared between a motor's
            two calibration runs by ``calibration.share_setpoint_step``); optionally
            the speed loop's quantisation ripple in a current sampled at one instant
            (``SPEED_ERR``, from the speed estimate the drive reports, shared alike).

``check_excitation`` refuses data that cannot identify b2 (constant speed, no
acceleration content, ill-conditioned regressors) with an ``ExcitationError`` saying
what to change.

Layout: ``result`` (the result type and parameter names), ``signals`` (one run through
the FIR, its cutoff), ``samples`` (which samples the equation holds on), ``drive_loop``
(what a drive's declared loop adds to its current), ``solve`` (the regressions),
``cogging`` (the harmonics kept), ``checks`` (refusals), ``default`` (the default fit,
its form spread and cross-check), ``paper`` (the paper's method as published); this
module dispatches on the method (``identify``, ``identify_trace``).
"""
from __future__ import annotations

from ...errors import TraceError
from .result import (BIAS, C_J, D_J, IdentificationResult, KT_J, LAG, LOAD_COS, LOAD_SIN,
                     SPEED_ERR, SP_STEP, TC_J, own_to_accel_names, physical_parameters)
from .signals import (MIN_FILTER_RUNS, MOTION_BAND_FACTOR, MOTION_BAND_SHARE, default_cutoff,
                      motion_band_hz)
from .samples import (CREEP_TOP_FRACTION, PUSHED_MIN_SAMPLES, REVERSAL_TOP_FRACTION,
                      SHORT_SPEED_SPAN, STANDSTILL_COUNTS_PER_SAMPLE, STANDSTILL_TOP_FRACTION,
                      STICK_BAND, STICK_MARGIN_S, STICK_MARGIN_SAMPLES, STUCK_CURRENT_SIGMAS,
                      count_reversals, encoder_resolution, equation_weight, smoothing_half_width,
                      speed_range, standstill_speed, top_speed)
from .drive_loop import (DRIVE_LOOP_KEYS, LOOP_DRIVE_KINDS, PERIOD_KICK_FINE, PERIOD_KICK_PERIODS,
                         PERIOD_KICK_WEIGHTS, declared_kick, declared_period_kick, drive_sampling,
                         interpolated_kink_weights, is_speed_command, kick_coefficient,
                         kick_speed_response, period_mean_kick_weights, speed_ripple_to_noise)
from .cogging import (COGGING_CANDIDATES, COGGING_MIN_WALD, COGGING_SCREEN, MAX_COGGING_ORDER,
                      MIN_SCREEN_ORDERS, cogging_candidates, cogging_order_scores)
from .checks import (MAX_B2_REL_STD, MAX_CONDITION, MIN_ACCEL_SNR, MIN_R2_SHARE, b2_shortfall,
                     check_excitation, check_fit_quality)
from .default import (AUTO_FORM, FORMS, FORM_SPREAD, FORM_SPREAD_MAX_SHARE, LEFT_OUT_WARN_SHARE,
                      identify_default)
from .paper import identify_paper


def identify(time_s, position_rad, current_a, *, method: str = "default",
             source: str = "<array>", **options) -> IdentificationResult:
    """Dispatch on ``method``: ``default`` (form ``auto``), ``accel``, ``torque``, ``iv``
    (``identify_default`` in that form), ``paper`` (data rate) or ``paper-15ms``.

    Parameters
    ----------
    time_s, position_rad, current_a : the run's samples.
    method : one of ``METHODS``.
    source : the run's name for messages.
    **options : passed to the method's function.

    Returns
    -------
    IdentificationResult

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md); M. Gautier and W. Khalil, "On the identification of the inertial parameters of robots", Proc. 27th IEEE Conf. Decision and Control, 1988, pp. 2264-2269

    Examples
    --------
    >>> fit = identify(t, theta, i, method="torque")   # doctest: +SKIP

    """
    if method == "default":
        return identify_default(time_s, position_rad, current_a, source=source, **options)
    if method in ("accel", "torque", "iv"):
        return identify_default(time_s, position_rad, current_a, source=source, form=method,
                                **options)
    options.pop("command", None)
    options.pop("load_rad_per_unit", None)
    if method == "paper":
        return identify_paper(time_s, position_rad, current_a, source=source, **options)
    if method == "paper-15ms":
        return identify_paper(time_s, position_rad, current_a, decimate_s=0.015,
                              source=source, **options)
    raise ValueError(f"unknown identification method {method!r}; use {', '.join(METHODS)}")


METHODS = ("default", "accel", "torque", "iv", "paper", "paper-15ms")


def identify_trace(trace, *, method: str = "default", **options) -> IdentificationResult:
    """Validate a single-motor ``Trace`` (columns ``position_rad``, ``current_a``; a
    ``command`` column in velocity mode is the iv form's instrument) and fit it.

    Parameters
    ----------
    trace : a single-motor ``Trace``.
    method : one of ``METHODS``.
    **options : passed on (``identify_default``'s options).

    Returns
    -------
    IdentificationResult

    References
    ----------
    M. Gautier and W. Khalil, "On the identification of the inertial parameters of robots", Proc. 27th IEEE Conf. Decision and Control, 1988, pp. 2264-2269

    Examples
    --------
    >>> fit = identify_trace(Trace.read("run.csv"))   # doctest: +SKIP

    """
    trace.validate(["position_rad", "current_a"], min_samples=50)
    # the iv form asks for the command; the default form takes it when the trace says it
    # is a speed setpoint (it is not used there, but reported with the fit's inputs)
    if "command" in trace and "command" not in options and (
            method == "iv" or (method in ("default", "torque") and is_speed_command(trace))):
        options["command"] = trace["command"]
    if "current_period_mean" not in options and method in ("default", "accel", "torque", "iv"):
        options["current_period_mean"] = (trace.meta.get("drive") or {}).get("current") == "mean"
    if ("period_kick_weights" not in options and "command" in trace and is_speed_command(trace)
            and method in ("default", "accel", "torque", "iv")):
        # a drive that steps its setpoint and reports the period mean, or ramps it and
        # reports an instant (its declared loop): its kicks need the command, in every form
        weights = declared_period_kick(trace)
        if weights is not None:
            options["period_kick_weights"] = weights
            options.setdefault("command", trace["command"])
            # an instant sample at the drive's declared limit: clipped, no kinks there
            # (``_below_current_limit``); a period mean below it may still hold a clipped
            # kick, and the test on it made such drives' Kt worse (250 Hz, seeds 7 and 8:
            # coverage 87.8/90.7 → 79.6/83.3 %), so it is not tested there
            drive = trace.meta.get("drive") or {}
            if (drive.get("current") == "instant" and drive.get("current_limit_a") is not None
                    and options.get("current_limit_a") is None):
                try:
                    options["current_limit_a"] = float(drive["current_limit_a"])
                except (TypeError, ValueError):
                    raise TraceError(f"{trace.source}: meta drive.current_limit_a is "
                                     f"{drive['current_limit_a']!r}; give the drive's current limit "
                                     f"in A (or leave it out)") from None
    if options.pop("speed_error", False) and "velocity_rad_s" in trace:
        options["drive_velocity_rad_s"] = trace["velocity_rad_s"]
    return identify(trace.time_s, trace["position_rad"], trace["current_a"], method=method,
                    source=trace.source, **options)


__all__ = [
    "AUTO_FORM",
    "BIAS",
    "COGGING_CANDIDATES",
    "COGGING_MIN_WALD",
    "COGGING_SCREEN",
    "CREEP_TOP_FRACTION",
    "C_J",
    "DRIVE_LOOP_KEYS",
    "D_J",
    "FORMS",
    "FORM_SPREAD",
    "FORM_SPREAD_MAX_SHARE",
    "IdentificationResult",
    "KT_J",
    "LAG",
    "LEFT_OUT_WARN_SHARE",
    "LOAD_COS",
    "LOAD_SIN",
    "LOOP_DRIVE_KINDS",
    "MAX_B2_REL_STD",
    "MAX_COGGING_ORDER",
    "MAX_CONDITION",
    "METHODS",
    "MIN_ACCEL_SNR",
    "MIN_FILTER_RUNS",
    "MIN_R2_SHARE",
    "MIN_SCREEN_ORDERS",
    "MOTION_BAND_FACTOR",
    "MOTION_BAND_SHARE",
    "PERIOD_KICK_FINE",
    "PERIOD_KICK_PERIODS",
    "PERIOD_KICK_WEIGHTS",
    "PUSHED_MIN_SAMPLES",
    "REVERSAL_TOP_FRACTION",
    "SHORT_SPEED_SPAN",
    "SPEED_ERR",
    "SP_STEP",
    "STANDSTILL_COUNTS_PER_SAMPLE",
    "STANDSTILL_TOP_FRACTION",
    "STICK_BAND",
    "STICK_MARGIN_S",
    "STICK_MARGIN_SAMPLES",
    "STUCK_CURRENT_SIGMAS",
    "TC_J",
    "b2_shortfall",
    "check_excitation",
    "check_fit_quality",
    "cogging_candidates",
    "cogging_order_scores",
    "count_reversals",
    "declared_kick",
    "declared_period_kick",
    "default_cutoff",
    "drive_sampling",
    "encoder_resolution",
    "equation_weight",
    "identify",
    "identify_default",
    "identify_paper",
    "identify_trace",
    "interpolated_kink_weights",
    "is_speed_command",
    "kick_coefficient",
    "kick_speed_response",
    "motion_band_hz",
    "own_to_accel_names",
    "period_mean_kick_weights",
    "physical_parameters",
    "smoothing_half_width",
    "speed_range",
    "speed_ripple_to_noise",
    "standstill_speed",
    "top_speed",
]
