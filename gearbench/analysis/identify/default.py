"""The default identification: the torque-side fit, its form spread, the plain
torque-side cross-check it always runs, and the checks (``identify_default``)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from ...errors import ExcitationError
from ..uncertainty import block_covariance, covariance_block, coverage_factor
from .checks import MAX_B2_REL_STD, _check, _condition_gram, _r2
from .cogging import _select_cogging
from .result import (C_J, D_J, IdentificationResult, KT_J, LAG, SPEED_ERR, SP_STEP, TC_J,
                     own_to_accel_names)
from .signals import _Signals, _prepare
from .solve import _Fit, _base_columns, _fit, _load_columns, _to_accel_names


LEFT_OUT_WARN_SHARE = 0.25   # warn when more of the run than this is left out


# ------------------------------------------------------------------------- default
# Equation forms (``identify_default(form=...)``), compared in ``bench accuracy``/``robustness``:
#   accel   θ'' = b2 i − (D/J)θ' − (Tc/J)s − …   least squares, errors in the current regressor
#           corrected for white current noise (the form this module started with);
#   torque  i = (J/Kt)θ'' + (D/Kt)θ' + (Tc/Kt)s + …   inverse-dynamics least squares as robotics
#           uses it (IDIM-LS, Gautier & Khalil 1988; Janot, Vandanjon & Gautier 2014): the
#           current, noisy and carrying whatever the model lacks, is the dependent variable;
#   iv      the torque form with instrumental variables built from the recorded speed command
#           (its filtered value, derivative and sign), which no disturbance inside the loop
#           can reach (Janot et al. 2014, IDIM-IV; Söderström & Stoica 1989, ch. 8).
FORMS = ("auto", "accel", "torque", "iv")
# Chosen from the measurements in ``bench accuracy`` (real section: robot joints at 100 Hz,
# EMPS at 1 kHz/250 Hz/100 Hz) and ``bench robustness --methods accel,torque,iv``: the
# torque form matches the accel form on the random plants and is right where the accel
# form fails (friction-dominated joints: J 4-5x too large); iv is unbiased there too but
# its intervals are 1.5-3x wider, so fewer runs meet the targets.
AUTO_FORM = "torque"
# Share of the two regression directions' difference added as model-error variance:
# (Δ/2)², the variance of a value anywhere between them (as calibration.LOSS_RUN_SPREAD).
FORM_SPREAD = 0.25
# ... unless the other direction's key regressor carries more than this share of noise:
# then it is attenuated by errors in variables (friction-dominated robot joints: accel form
# 0.12-5.5) and its difference says nothing about this fit's model error (random plants
# at 1 kHz: <= 0.05)
FORM_SPREAD_MAX_SHARE = 0.1


def identify_default(time_s: np.ndarray, position_rad: np.ndarray, current_a: np.ndarray, *,
                     cutoff_hz: float | None = None, spring: bool = False,
                     friction_width_rad_s: float = 0.0, bias: bool | None = None,
                     lag: bool = True, eiv_correction: bool = True,
                     cogging: bool | tuple[int, ...] = True, check: bool = True,
                     source: str = "<array>", rad_per_unit: float | None = 1.0,
                     form: str = "auto", command: np.ndarray | None = None,
                     load_rad_per_unit: float | None = None,
                     form_spread: bool = True, setpoint_step: bool = False,
                     current_limit_a: float | None = None,
                     kick_a_per_rad_s: float | None = None,
                     drive_velocity_rad_s: np.ndarray | None = None,
                     current_period_mean: bool = False,
                     period_kick_weights: np.ndarray | None = None) -> IdentificationResult:
    """Bias-reduced fit of ``J θ'' + D θ' + Tc s(θ') [+ C θ] [+ q·(sin, cos) θ_L] = Kt i [+ c]``.

    Every run is fitted twice: in ``form`` and, as a cross-check, by the plain filtered
    torque-side least squares (IDIM-LS); both are reported (``extras["cross_check"]``),
    with a verdict when they disagree beyond their intervals.

    Parameters
    ----------
    time_s, position_rad, current_a : the run's samples (angle in radians of the motor,
        or the user's unit with ``rad_per_unit``; current or force).
    cutoff_hz : low-pass cutoff of the common FIR; default ``default_cutoff``: min(40 Hz,
        rate/10, 10 x the motion's band).
        Applied to both sides of a linear relation, the filter never biases the fit.
    spring : also fit the paper's C/J (spring to ground); off for a real motor.
    friction_width_rad_s : 0 (default): s(θ') is sign(θ') with each reversal at its
        sub-sample instant (``derivatives.coulomb_regressor``); > 0: the older tanh(θ'/w).
    bias : constant current offset. Default: only when the speed reverses (with one
        direction an offset and Coulomb friction are one column, PAPER-NOTES).
    lag : fit a lag τ of the measured current behind the torque-producing one,
        i_T(t) ≈ i(t + τ) (``extras["current_delay_s"]``, τ > 0: the current is late).
    eiv_correction : errors-in-variables correction of the regressor that carries the
        noise (accel form: white current noise; torque form: encoder noise on θ'').
    cogging : sin/cos(k θ) cogging orders per motor revolution; ``True``: screened
        (``cogging_order_scores``) and kept by a Wald test (BIC price and
        ``COGGING_MIN_WALD``); a tuple: exactly those; ``False``: none.
    rad_per_unit : motor radians per position unit (None: no cogging terms).
    form : ``accel``, ``torque``, ``iv`` (see ``FORMS``) or ``auto`` (``AUTO_FORM``,
        chosen from the benchmark tables).
    command : the recorded speed command (same unit as the angle per second), the
        instrument of the iv form.
    load_rad_per_unit : load angle per position unit (1 for a load-side angle, 1/ratio
        for a motor angle behind a gear): adds a position-dependent load torque of
        order 1, q_s sin θ_L + q_c cos θ_L (gravity, unbalance, an eccentric load),
        reported as ``load_sin``/``load_cos`` — distinct from cogging (motor angle).
    setpoint_step : add the speed setpoint's step per SYNC, Δcmd/dt (``command``
        needed), as a regressor ``setpoint_step``: the current kick of a drive that
        steps its setpoint without interpolation (``_setpoint_steps``). Nearly collinear
        with θ'' within one run; ``calibrate_motor`` turns it on and shares it between
        its two runs.
    current_limit_a : the drive's current limit (its description's ``current_limit_a``,
        CiA 402 max current 0x6073), or None: at a sample at the limit the
        ``setpoint_step`` regressor is 0 (``_below_current_limit``).
    kick_a_per_rad_s : the drive's known setpoint-step kick c (``kick_coefficient``, from
        its declared loop): c·Δcmd is added to the sampled current (0 at the current
        limit) instead of fitting a ``setpoint_step`` term.
    drive_velocity_rad_s : the speed estimate the drive reports with each sample (same
        unit as the angle per second): adds the speed loop's ripple regressor
        ``speed_error`` (``SPEED_ERR``) on a run that does not reverse; for a drive that
        samples its current at one instant (``calibrate_motor`` passes it then).
    current_period_mean : each current sample is the mean over the period ending at it
        (a drive that says ``current: mean``; ``identify_trace`` reads it from the
        trace's drive description): matched by ``derivatives.match_period_means``.
    period_kick_weights : with ``command``: what the current's match misses of the speed
        setpoint's shape within each period, added to the matched current — a stepping
        drive's kicks with ``current_period_mean`` (``period_mean_kick_weights``), an
        interpolating drive's kinks with instant samples (``interpolated_kink_weights``);
        ``identify_trace`` computes them from the drive's declared loop.
    form_spread : also fit the other regression direction (accel for the torque side,
        and vice versa) with the same terms and add ``FORM_SPREAD``·ΔΔᵀ of their
        difference Δ in (Kt/J, D/J, Tc/J) to the covariance: with a correct model both
        directions estimate the same parameters, so what separates them beyond noise is
        model error (closed-loop friction transitions, unmodelled current content) that
        the block covariance cannot see (``extras["form_spread"]``).

    Returns
    -------
    IdentificationResult
        On the accel-form names (``Kt/J``, ``D/J``, ``Tc/J``, …) whatever the form,
        with a covariance from overlapping window sums of residual scores (valid for coloured
        residuals); ``extras["identified"]`` says per parameter whether the run
        identifies it (95 % interval excluding zero, Kt/J to ``MAX_B2_REL_STD``).

    References
    ----------
    Yukawa, Ohishi, Katsura et al., "Identification of motor parameters …" (the
    paper's method, ``identify_paper``); M. Gautier and W. Khalil, "On the
    identification of the inertial parameters of robots", Proc. 27th IEEE CDC, 1988,
    pp. 2264–2269 (IDIM-LS); A. Janot, P.-O. Vandanjon and M. Gautier, "A generic
    instrumental variable approach for industrial robot identification", IEEE Trans.
    Control Syst. Technol. 22(1), 2014, pp. 132–145 (IDIM-IV).

    Examples
    --------
    >>> fit = identify_default(t, theta, i, load_rad_per_unit=1.0)   # doctest: +SKIP
    >>> fit.b2, fit.extras["cross_check"]["agree"]                   # doctest: +SKIP
    """
    if form not in FORMS:
        raise ValueError(f"unknown form {form!r}; use one of {', '.join(FORMS)}")
    sig = _prepare(np.asarray(time_s, float), np.asarray(position_rad, float),
                   np.asarray(current_a, float), cutoff_hz=cutoff_hz,
                   friction_width_rad_s=friction_width_rad_s, command=command, source=source,
                   current_limit_a=current_limit_a, kick_a_per_rad_s=kick_a_per_rad_s,
                   drive_velocity=drive_velocity_rad_s, current_mean=current_period_mean,
                   period_kick=period_kick_weights)
    use_bias = sig.reverses if bias is None else bias
    if use_bias and not sig.reverses:
        raise ExcitationError(f"{source}: a current offset and Coulomb friction cannot be told "
                              f"apart without speed reversals; reverse the rotation in the run "
                              f"or fit without the offset term")
    label = "default" if form == "auto" else form
    if form == "auto":
        form = AUTO_FORM
    if setpoint_step and command is None:
        raise ExcitationError(f"{source}: the setpoint-step term needs the recorded speed "
                              f"command (column 'command'); record it or fit without the term")
    opts = dict(spring=spring, use_bias=use_bias, lag=lag, eiv=eiv_correction, cogging=cogging,
                rad_per_unit=rad_per_unit, load_rad_per_unit=load_rad_per_unit,
                setpoint_step=setpoint_step,
                speed_error=drive_velocity_rad_s is not None and not sig.reverses)
    # with the drive's kick added to the current (its declared loop), the accel form's Kt/J
    # is off by what that kick does to a regressor: a stepping, instant-sampling drive's
    # reversing runs (robustness seed 7) put its calibrated Kt 0.04-0.34 % below the torque
    # form's whatever the noise, encoder, cogging or friction smoothing (an interpolating
    # or averaging drive on the same runs: 0.001-0.003 %; current lag -> 0: 0.66 %), so its
    # difference is no model error of this fit (``calibrate_motor`` skips it as a variant)
    kicked = bool(kick_a_per_rad_s) and command is not None
    fit = _identify_checked(sig, form, label, opts, check=check,
                            form_spread=form_spread and not kicked)
    if form_spread and kicked:
        fit.extras["form_spread"] = {"skipped": "the drive's kick is added to the current: the "
                                                "other direction's difference is its own"}
    return fit


def _identify_checked(sig: _Signals, form: str, label: str, opts: dict, *, check: bool,
                      form_spread: bool) -> IdentificationResult:
    """``form`` on prepared signals, its form spread, the plain torque-side cross-check,
    the fallback to the cross-check where only it identifies Kt/J, and the checks."""
    main = replace(_identify_form(sig, form, **opts), method=label)
    other = None
    if form_spread:
        # the other regression direction, same terms: their spread is model error
        orders = tuple(main.extras["cogging"]) or False
        other = _identify_form(sig, "accel" if form != "accel" else "torque",
                               **{**opts, "cogging": orders})
        main = _with_form_spread(main, other)
    plain = replace(_identify_form(sig, "torque", **{**opts, "eiv": False, "lag": False,
                                                     "cogging": False, "setpoint_step": False,
                                                     "speed_error": False}),
                    method="torque-ls")
    cross = _cross_check(main, plain)
    chosen = main
    # (not with the setpoint-step term: its collinearity with θ'' is resolved across
    # the two calibration runs, ``calibration.share_setpoint_step``)
    if (not main.extras["identified"][KT_J] and plain.extras["identified"][KT_J]
            and not opts.get("setpoint_step")):
        # the textbook fit may identify what this one cannot (with the same model-error term)
        alt = _with_form_spread(plain, other) if other is not None else plain
        if alt.extras["identified"][KT_J]:
            chosen = alt
            cross["returned"] = plain.method
    if check:
        _check(sig, chosen)
    chosen.extras["cross_check"] = cross
    left_out = float(1.0 - np.mean(sig.moving))
    chosen.extras["left_out_share"] = left_out
    if left_out > LEFT_OUT_WARN_SHARE:
        chosen.extras.setdefault("warnings", []).append(
            f"the rotor sticks or breaks away on {100 * left_out:.0f} % of the run; those "
            f"samples carry no Kt information and are left out of the fit (its intervals "
            f"count only the rest): move faster through zero speed or avoid the stops")
    return chosen


def _identify_form(sig: _Signals, form: str, *, spring, use_bias, lag, eiv, cogging,
                   rad_per_unit, load_rad_per_unit, setpoint_step=False,
                   speed_error=False) -> IdentificationResult:
    """One formulation on prepared signals → an ``IdentificationResult`` (no checks)."""
    cols = _base_columns(sig, form, spring=spring, use_bias=use_bias)
    n_base = len(cols)
    cols += _load_columns(sig, load_rad_per_unit, form)
    if setpoint_step and "setpoint_step" in sig.fs:
        cols.append((SP_STEP, sig.fs["setpoint_step"], 1.0 if form == "accel" else -1.0))
    if speed_error and "drive_velocity" in sig.fs:
        cols.append((SPEED_ERR, sig.fs["drive_velocity"] - sig.fs["velocity"],
                     1.0 if form == "accel" else -1.0))
    fit = _fit(sig, cols, form, lag=lag, eiv=eiv)
    block = covariance_block(fit.residual, len(sig.taps))
    fit, orders = _select_cogging(sig, cols, form, fit, cogging, rad_per_unit, lag, eiv, block)
    e = fit.residual
    cov_own, dof, n_eff = block_covariance(fit.Xt, e, fit.A, block=block, Z=fit.Z)
    names, values, cov = _to_accel_names(fit, cov_own)
    b2 = float(values[0])
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    tq = coverage_factor(dof)
    identified = {nm: bool(abs(v) > tq * s) for nm, v, s in zip(names, values, std)}
    identified[KT_J] = bool(b2 > 0 and std[0] <= MAX_B2_REL_STD * b2)
    cog_amps = {int(k): float(np.hypot(values[names.index(f"cog{k}_sin")],
                                       values[names.index(f"cog{k}_cos")])) for k in orders}
    share = _regressor_noise_share(sig, fit, b2)
    per_ampere = {}
    if form != "accel":
        # the torque side's own coefficients: friction per ampere is identified even when
        # the inertia is not (its uncertainty does not pass through J)
        for k, nm in enumerate(("J/Kt", "D/Kt", "Tc/Kt")):
            per_ampere[nm] = [float(fit.beta[k]), float(np.sqrt(max(cov_own[k, k], 0.0)))]
    spring_v = values[names.index(C_J)] if spring else 0.0
    lag_v = float(values[names.index(LAG)]) if LAG in names else 0.0
    return IdentificationResult(
        method=form, names=names,
        values=tuple(map(float, values)), covariance=cov, dof=dof, dt_s=sig.dt,
        n_samples=sig.n, n_effective=n_eff, r2=_r2(fit.y, e),
        rmse=float(np.sqrt(np.mean(e * e))), condition=_condition_gram(fit.G[:n_base, :n_base]),
        A=np.array([[0.0, 1.0], [-spring_v, -values[1]]]), B=np.array([0.0, b2]),
        extras={"form": fit.form, "cutoff_hz": sig.cutoff_hz, "filter_taps": len(sig.taps),
                "current_noise_a": float(np.sqrt(sig.noise_var_raw)), "cogging": cog_amps,
                "speed_range_rad_s": sig.speed_range,
                "current_delay_s": fit.shift_s + (lag_v / b2 if b2 else 0.0),
                "identified": identified, "regressor_noise_share": share,
                "per_ampere": per_ampere,
                # the form's own coefficients and covariance (calibration combines two runs there)
                "own_form": {"names": list(names), "beta": fit.beta.tolist(),
                             "sign": [c[2] for c in fit.cols] + [1.0] * (len(names) - len(fit.cols)),
                             "cov": cov_own.tolist()},
                "residual_unit": "rad/s^2" if form == "accel" else "A"})


def _with_form_spread(main: IdentificationResult, other: IdentificationResult) -> IdentificationResult:
    """``main`` with ``FORM_SPREAD``·ΔΔᵀ added to its (Kt/J, D/J, Tc/J) covariance, Δ the
    difference to ``other`` (the opposite regression direction, same terms), and its
    per-parameter identifiability re-judged with the wider intervals."""
    share = other.extras["regressor_noise_share"]
    if share > FORM_SPREAD_MAX_SHARE:
        return replace(main, extras={**main.extras, "form_spread": {
            "other": other.method, "skipped": f"its key regressor's noise share {share:.3g} > "
            f"{FORM_SPREAD_MAX_SHARE:g}: the difference is its errors in variables, not model error"}})
    names = [n for n in (KT_J, D_J, TC_J) if n in main.names and n in other.names]
    idx = [main.names.index(n) for n in names]
    delta = np.array([main.value(n) - other.value(n) for n in names])
    cov = main.covariance.copy()
    cov[np.ix_(idx, idx)] += FORM_SPREAD * np.outer(delta, delta)
    identified = dict(main.extras["identified"])
    tq = coverage_factor(main.dof)
    for n, k in zip(names, idx):
        identified[n] = bool(abs(main.values[k]) > tq * np.sqrt(cov[k, k]))
    b2, b2_std = main.values[idx[0]], float(np.sqrt(cov[idx[0], idx[0]]))
    identified[KT_J] = bool(b2 > 0 and b2_std <= MAX_B2_REL_STD * b2)
    extras = {**main.extras, "identified": identified,
              "form_spread": {"other": other.method, "difference": dict(zip(names, map(float, delta)))}}
    if main.extras.get("per_ampere") and len(names) == 3:
        # the torque side's own coefficients (J/Kt, D/Kt, Tc/Kt) = (1, D/J, Tc/J)/b2 carry
        # the same spread (that map is its own inverse: ``own_to_accel_names`` maps it)
        _, spread = own_to_accel_names("torque", [main.value(n) for n in names], np.ones(3),
                                       FORM_SPREAD * np.outer(delta, delta))
        extras["per_ampere"] = {k: [v, float(np.sqrt(s * s + spread[j, j]))]
                                for j, (k, (v, s)) in enumerate(main.extras["per_ampere"].items())}
    return replace(main, covariance=cov, extras=extras)


def _regressor_noise_share(sig: _Signals, fit: _Fit, b2: float) -> float:
    """Variance of what disturbs the key regressor (current for the accel form: the
    residual in current units, e/b2; θ'' for the torque form: encoder noise) over that
    regressor's variance not explained by the other columns: to first order the
    fraction by which least squares attenuates its coefficient (errors in variables)."""
    try:
        partial = 1.0 / np.linalg.inv(fit.G)[0, 0] / sig.n
    except np.linalg.LinAlgError:
        return float("inf")
    if fit.form == "accel":
        e = fit.residual / b2 if b2 else fit.residual
        noise = float(np.mean(e * e))
    else:
        noise = sig.accel_noise ** 2
    return float(noise / partial) if partial > 0 else float("inf")


def _cross_check(main: IdentificationResult, other: IdentificationResult) -> dict:
    """Both fits' Kt/J, D/J, Tc/J with standard uncertainties; where they differ beyond
    2 sigma of the two (taken independent: conservative for one data set) the verdict
    says which one the data supports and why:

    * the fit whose key regressor carries the smaller share of noise (errors in
      variables attenuate its coefficient by about that share: current content the
      model lacks for the accel form, encoder noise on θ'' for the torque form), and
    * for two torque-side fits, the one whose extra terms (current lag, cogging) are
      significant."""
    out = {"method": other.method, "agree": True, "differ": [],
           "noise_share": {main.method: main.extras["regressor_noise_share"],
                           other.method: other.extras["regressor_noise_share"]}}
    for nm in (KT_J, D_J, TC_J):
        a, b = main.value(nm), other.value(nm)
        s = float(np.hypot(main.std(nm), other.std(nm)))
        out[nm] = {main.method: a, other.method: b, "std": s}
        if abs(a - b) > 2.0 * s and s > 0:
            out["agree"] = False
            out["differ"].append(nm)
    if out["agree"]:
        out["verdict"] = "the two fits agree within their intervals"
        return out
    sm, so = main.extras["regressor_noise_share"], other.extras["regressor_noise_share"]
    extra = [nm for nm in main.names if nm not in other.names and main.extras["identified"].get(nm)]
    if main.extras["form"] == other.extras["form"]:
        best = main.method if extra else other.method
        why = (f"{main.method}'s added terms {', '.join(extra)} are significant" if extra else
               f"{main.method}'s added terms are not significant")
    else:
        best = main.method if sm <= so else other.method
        why = (f"noise share of the key regressor {sm:.3g} ({main.method}) vs {so:.3g} "
               f"({other.method}): errors in variables attenuate the other fit")
    out["supported"] = best
    out["verdict"] = (f"{main.method} and {other.method} differ on {', '.join(out['differ'])} "
                      f"beyond their intervals; the data supports {best}: {why}")
    return out
