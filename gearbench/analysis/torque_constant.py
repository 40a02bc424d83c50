"""Torque constant from two runs, one with a known inertia disk (paper eqs. 11–17).

Run 1 (motor alone) gives b2~ = Kt/J (eq. 11); run 2 (disk j added) gives
b2^ = Kt/(J + j) (eq. 15). Eliminating J:

    Kt = j · b2~ · b2^ / (b2~ − b2^)          (eq. 17, corrected)

The paper prints eq. 16 as b2^ = Kt/(b2~ + j) and eq. 17 with the denominator
(b2^ − b2~), which is negative for any real disk; ``paper_printed_eq17`` keeps that
form only so a test can show it. Rotor inertia follows as J = Kt / b2~.

Uncertainty = statistical part (each run's block covariance of b2) + a model-error
part: a relative error ``MODEL_B2_REL`` on b2 that the two runs do not share, i.e.
σ_model = MODEL_B2_REL · Kt / (1 − b2^/b2~) (a relative error ε on b2^ alone moves Kt
by ε/(1 − b2^/b2~); an error common to both runs cancels). Why: repeating a robustness
plant with fresh noise shows the Kt misses are deterministic, not noise — e.g. a drive
that steps its speed setpoint every SYNC and reports an instantaneous current sample
biases b2 by 1-3 %, mostly the same in both runs (it cancels in eq. 17) but not entirely
(the loaded run tracks the command differently), leaving 0.1-0.7 % on Kt that no split
of a run can see (that effect is now fitted, ``calibration.share_setpoint_step``, whose
correlated b2 enter through ``b2_covariance``; the term stays for what is left). Kt is proportional to the disk's inertia j, so j's own relative
standard uncertainty adds 1:1 to Kt's (u_rel(Kt)² gains u_rel(j)²). The interval is
Student-t with Welch–Satterthwaite degrees of freedom, the model and disk parts
counting as known (``gearbench.analysis.uncertainty``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ExcitationError, GearbenchError
from .identify import IdentificationResult
from .uncertainty import DOF_MAX, interval

# Relative b2 error not shared by the two runs (1 sigma). Chosen on robustness seed 0
# (Kt coverage 84 % -> 94 %), checked on seeds 1-3 (see the robustness benchmark).
# ``calibration.calibrate_motor`` replaces it for the default method by the runs' own Kt
# spread under other models (``calibration.MODEL_VARIANTS``).
MODEL_B2_REL = 5e-4


@dataclass(frozen=True)
class TorqueConstant:
    """Kt and rotor inertia with 95 % intervals (Student-t, ``dof`` degrees of freedom).

    ``torque_constant_std`` is the total standard uncertainty, the root sum of squares
    of ``statistical_std`` (noise, from the runs' covariances), ``model_std`` (b2 model
    error), ``disk_std`` (the disk inertia's own uncertainty, Kt·u(j)/j) and ``form_std``
    (the runs' regression-direction spread moved through eq. 17 together)."""

    torque_constant_nm_a: float
    torque_constant_ci95: tuple[float, float]
    torque_constant_std: float
    rotor_inertia_kgm2: float
    rotor_inertia_std: float
    dof: int
    statistical_std: float = 0.0
    model_std: float = 0.0
    disk_std: float = 0.0
    form_std: float = 0.0


def torque_constant_from_b2(b2_unloaded: float, b2_loaded: float, disk_inertia_kgm2: float) -> float:
    """Corrected eq. 17: ``Kt = j b2~ b2^ / (b2~ − b2^)``.

    Parameters
    ----------
    b2_unloaded, b2_loaded : Kt/J without and with the disk.
    disk_inertia_kgm2 : the disk's inertia j.

    Returns
    -------
    float
        Kt, N m/A.

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md), eq. 17 (corrected)

    Examples
    --------
    >>> round(torque_constant_from_b2(2.0, 1.0, 1.0), 6)
    2.0

    """
    return disk_inertia_kgm2 * b2_unloaded * b2_loaded / (b2_unloaded - b2_loaded)


def paper_printed_eq17(b2_unloaded: float, b2_loaded: float, disk_inertia_kgm2: float) -> float:
    """Eq. 17 as printed (denominator b2^ − b2~): negative Kt. For tests only.

    Parameters
    ----------
    b2_unloaded, b2_loaded, disk_inertia_kgm2 : as ``torque_constant_from_b2``.

    Returns
    -------
    float
        The printed formula's (negative) value.

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md), eq. 17 as printed

    Examples
    --------
    >>> paper_printed_eq17(2.0, 1.0, 1.0)
    -2.0

    """
    return disk_inertia_kgm2 * b2_unloaded * b2_loaded / (b2_loaded - b2_unloaded)


def torque_constant(unloaded: IdentificationResult, loaded: IdentificationResult,
                    disk_inertia_kgm2: float, *, disk_inertia_std: float = 0.0,
                    model_b2_rel: float | None = None, unloaded_name: str = "unloaded run",
                    loaded_name: str = "loaded run", b2_covariance: float = 0.0,
                    b2_form_shift: tuple[float, float] = (0.0, 0.0)) -> TorqueConstant:
    """Kt from two fits (corrected eq. 17) with its uncertainty by first-order propagation.

    With u = 1/b2^ − 1/b2~ = j/Kt:  ∂Kt/∂b2~ = −Kt²/(j b2~²),  ∂Kt/∂b2^ = Kt²/(j b2^²),
    ∂Kt/∂j = Kt/j; the two runs are independent. ``disk_inertia_std`` is the disk's
    standard uncertainty (kg m², see ``uncertainty.tolerance_std``). ``model_b2_rel`` adds a relative
    error of that size on b2 not shared by the runs, σ = ε·Kt/(1 − b2^/b2~) (module
    docstring), largest when the disk is light (None: ``MODEL_B2_REL``). The interval is
    Student-t with ν = σ⁴/(σ_stat⁴/ν_stat) (Welch–Satterthwaite), ν_stat the smaller of
    the two runs' degrees of freedom.

    Parameters
    ----------
    unloaded, loaded : the two runs' fits.
    disk_inertia_kgm2, disk_inertia_std : the disk's inertia and its standard uncertainty.
    model_b2_rel : relative b2 model error not shared by the runs (None: ``MODEL_B2_REL``).
    b2_covariance : covariance of the two runs' b2 (fits that share a parameter,
        ``calibration.share_setpoint_step``; 0: independent runs).
    b2_form_shift : one model error's standard shift of each run's b2, signed, taken
        together: σ_form = |∂Kt/∂b2~·s~ + ∂Kt/∂b2^·s^| (``calibration.calibrate_from_fits``
        passes the runs' regression-direction spread, ``identify.FORM_SPREAD``, which the
        runs' b2 covariances then leave out).
    unloaded_name, loaded_name : the runs' names for messages.

    Returns
    -------
    TorqueConstant

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md), eqs. 11-17; JCGM 100:2008, "Evaluation of measurement data — Guide to the expression of uncertainty in measurement" (GUM)

    Examples
    --------
    >>> tc = torque_constant(fu, fl, 2e-5)   # doctest: +SKIP

    """
    j = float(disk_inertia_kgm2)
    if not (j > 0) or not np.isfinite(j):
        raise GearbenchError(f"disk inertia must be a positive number of kg m^2, got {j!r}; "
                             f"pass the disk's inertia, e.g. --inertia 1.5e-5")
    bu, bl = unloaded.b2, loaded.b2
    if not (bu > 0 and bl > 0):
        raise ExcitationError(f"{unloaded_name if bu <= 0 else loaded_name}: identified Kt/J = "
                              f"{min(bu, bl):.4g} is not positive; check the current sign and "
                              f"the excitation")
    diff_std = float(np.sqrt(max(unloaded.b2_std ** 2 + loaded.b2_std ** 2 - 2 * b2_covariance,
                                 0.0)))
    if abs(bu - bl) < 3.0 * diff_std:
        # equal Kt/J within noise: the disk did not show, and Kt = j b2~ b2^/(b2~ - b2^) would be noise
        raise ExcitationError(
            f"{loaded_name} and {unloaded_name} give the same Kt/J ({bl:.5g} vs {bu:.5g}, difference "
            f"below 3 standard deviations {3 * diff_std:.2g}): the disk's inertia does not show; check "
            f"that the disk was mounted on this motor for the loaded run, or use a heavier disk")
    if bl >= bu:
        raise GearbenchError(
            f"{loaded_name} accelerates more per ampere (Kt/J = {bl:.5g}) than {unloaded_name} "
            f"({bu:.5g}), which would give a negative Kt: swap --loaded and --unloaded")
    kt = torque_constant_from_b2(bu, bl, j)
    dkt_dbu = -kt * kt / (j * bu * bu)
    dkt_dbl = kt * kt / (j * bl * bl)
    if model_b2_rel is None:
        model_b2_rel = MODEL_B2_REL
    if not (np.isfinite(disk_inertia_std) and disk_inertia_std >= 0):
        raise GearbenchError(f"disk inertia standard uncertainty must be >= 0 kg m^2, got "
                             f"{disk_inertia_std!r}")
    var_stat = max((dkt_dbu * unloaded.b2_std) ** 2 + (dkt_dbl * loaded.b2_std) ** 2
                   + 2 * dkt_dbu * dkt_dbl * b2_covariance, 0.0)
    var_disk = (kt / j * disk_inertia_std) ** 2
    var_model = (model_b2_rel * kt * bu / (bu - bl)) ** 2
    # one model (the other regression direction) shifts both runs at once: what it does to
    # Kt is the shifts moved through eq. 17 together, not each on its own (an additive J
    # error in both runs cancels: robustness seed 7 case 2's output motor, b2 +4.0 % and
    # +1.9 %, Kt −0.05 %)
    var_form = (dkt_dbu * b2_form_shift[0] + dkt_dbl * b2_form_shift[1]) ** 2
    var_known = var_disk + var_model + var_form
    std = float(np.sqrt(var_stat + var_known))
    dof_stat = int(min(unloaded.dof, loaded.dof))
    # Welch–Satterthwaite with the model and disk parts known (infinite dof)
    dof = dof_stat if var_stat <= 0 else int(min(
        (var_stat + var_known) ** 2 / (var_stat ** 2 / max(dof_stat, 1)), DOF_MAX))
    # J = Kt / b2~ :  dJ = dKt / b2~ − Kt dbu / b2~² (correlated through bu).
    jr = kt / bu
    dj_dbu = dkt_dbu / bu - kt / bu ** 2
    dj_dbl = dkt_dbl / bu
    j_std = float(np.sqrt(max((dj_dbu * unloaded.b2_std) ** 2 + (dj_dbl * loaded.b2_std) ** 2
                              + 2 * dj_dbu * dj_dbl * b2_covariance, 0.0)
                          + (jr / j * disk_inertia_std) ** 2
                          + (dj_dbu * b2_form_shift[0] + dj_dbl * b2_form_shift[1]) ** 2))
    return TorqueConstant(kt, interval(kt, std, dof), std, jr, j_std, dof,
                          float(np.sqrt(var_stat)), float(np.sqrt(var_model)), float(np.sqrt(var_disk)),
                          float(np.sqrt(var_form)))
