"""What an identification returns: ``IdentificationResult``, the parameter names, physical units."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np



# Regression written as  θ'' = b2·i − (D/J)·θ' − (Tc/J)·s(θ') − (C/J)·θ + bias.
KT_J, D_J, TC_J, C_J, BIAS, LAG = "Kt/J", "D/J", "Tc/J", "C/J", "bias", "lag"


@dataclass(frozen=True)
class IdentificationResult:
    """One run's fit. ``values``/``covariance`` follow ``names``; sign convention of
    the module docstring, so ``D/J`` and ``Tc/J`` are positive for a real motor."""

    method: str
    names: tuple[str, ...]
    values: tuple[float, ...]
    covariance: np.ndarray
    dof: int                     # degrees of freedom for Student-t intervals
    dt_s: float
    n_samples: int               # samples in the regression
    n_effective: float           # independent-sample equivalent (coloured residuals)
    r2: float
    rmse: float                  # rad/s² residual
    condition: float             # of the column-normalised regressor matrix
    A: np.ndarray                # 2x2 state matrix (paper eq. 4 / 10)
    B: np.ndarray                # input vector [b1, b2] (paper eq. 5 / 10)
    extras: dict = field(default_factory=dict)

    def value(self, name: str, default: float = 0.0) -> float:
        return self.values[self.names.index(name)] if name in self.names else default

    def std(self, name: str) -> float:
        if name not in self.names:
            return 0.0
        k = self.names.index(name)
        return float(np.sqrt(max(self.covariance[k, k], 0.0)))

    @property
    def b2(self) -> float:
        """Kt/J (paper eq. 11), 1/(A s²)."""
        return self.value(KT_J)

    @property
    def b2_std(self) -> float:
        return self.std(KT_J)

    def to_dict(self) -> dict:
        return {
            "method": self.method,
            "b2": self.b2, "b2_std": self.b2_std,
            "params": dict(zip(self.names, map(float, self.values))),
            "std": {n: self.std(n) for n in self.names},
            "covariance": {"names": list(self.names), "matrix": self.covariance.tolist()},
            "dof": self.dof, "dt_s": self.dt_s, "n_samples": self.n_samples,
            "n_effective": self.n_effective, "r2": self.r2, "rmse": self.rmse,
            "condition": self.condition,
            "A": self.A.tolist(), "B": self.B.tolist(),
            **{k: v for k, v in self.extras.items()},
        }
LOAD_SIN, LOAD_COS = "load_sin", "load_cos"
SP_STEP = "setpoint_step"
# The speed loop's encoder-quantisation ripple in a current sampled at one instant: the
# drive's P gain turns its speed estimate's count quantum into current, and the instant
# sample aliases that into the fit band, where it follows the motion (noise-free forward
# random plants: Kt off by 0.2-0.5 %, gone with a fine encoder or a period-mean current).
# Its regressor is e = F[v_drive] − F[θ'], the speed the drive reports (CiA 402 0x606C,
# ``velocity_rad_s``) less the encoder's, both through the fit's filter. e also holds the
# drive estimate's lag, −τ·θ'', so within one run its gain trades with J/Kt; one gain for
# both calibration runs (``calibration.share_setpoint_step``) puts the same γ·τ on both
# runs' J/Kt, which cancels in eq. 17. Not on reversing runs: around the zero crossing
# the drive's estimate and the encoder part for other reasons (seeds 7/8: helped 10, hurt 7
# reversing motors by > 0.05 % noise-free, against 12/3 forward).
SPEED_ERR = "speed_error"


def own_to_accel_names(form: str, beta, sign, cov) -> tuple[np.ndarray, np.ndarray]:
    """A form's own coefficients → values and covariance on the accel-form names.

    The accel form's coefficients times their signs; the torque/iv form's
    p = (J/Kt, D/Kt, …) mapped by v_0 = 1/p_0, v_k = s_k p_k / p_0 (delta method for
    the covariance).

    Parameters
    ----------
    form : ``accel``, ``torque`` or ``iv``.
    beta, sign, cov : the form's coefficients, their signs onto the accel names and
        their covariance (``extras["own_form"]`` of a fit).

    Returns
    -------
    (values, covariance) on the accel-form names.

    References
    ----------
    JCGM 100:2008 (GUM), 5.1.2 (first-order propagation)

    Examples
    --------
    >>> own_to_accel_names("torque", [0.5, 0.1], [1.0, 1.0], np.zeros((2, 2)))[0]
    array([2. , 0.2])
    """
    beta, sign, cov = np.asarray(beta, float), np.asarray(sign, float), np.asarray(cov, float)
    if form == "accel":
        return beta * sign, cov * np.outer(sign, sign)
    a = beta[0]
    values = sign * beta / a
    values[0] = 1.0 / a
    Jac = np.diag(sign / a)
    Jac[:, 0] = -values / a
    Jac[0, 0] = -1.0 / a ** 2
    return values, Jac @ cov @ Jac.T


def physical_parameters(fit: IdentificationResult, torque_per_ampere: float) -> dict:
    """Inertia, viscous and Coulomb friction in SI from a fit and a known torque per ampere.

    ``J θ'' + D θ' + Tc s(θ') = k i`` with k known (a motor's Kt for a motor angle; a
    robot joint's torque per ampere, gear included, for a joint angle; a force per
    ampere and a position in metres give kg, N s/m and N): J = k/b2, D = k·(D/J)/b2,
    Tc = k·(Tc/J)/b2, their standard uncertainties by the delta method on the fit's
    whole (Kt/J, D/J, Tc/J) covariance — correlations included, so a friction the run
    identifies keeps its own interval when the inertia is poorly known (to first order:
    the torque side's per-ampere coefficients with their model-error spreads). k is
    taken as exact; its relative tolerance adds in quadrature to each.

    Parameters
    ----------
    fit : an ``IdentificationResult`` with Kt/J, D/J and Tc/J.
    torque_per_ampere : k (N m/A, or N/A for a linear axis in metres).

    Returns
    -------
    dict
        ``{"J": (value, std), "D": (value, std), "Tc": (value, std)}``.

    References
    ----------
    JCGM 100:2008 (GUM), sec. 5.1.2 (law of propagation of uncertainty); M. Gautier and
    W. Khalil, "On the identification of the inertial parameters of robots", Proc. 27th
    IEEE CDC, 1988 (the torque-side model)

    Examples
    --------
    >>> physical_parameters(fit, 60.0)["J"]     # doctest: +SKIP
    (3.89, 0.18)
    """
    k = float(torque_per_ampere)
    if not (np.isfinite(k) and k > 0):
        raise ValueError(f"torque per ampere must be a positive number, got {torque_per_ampere!r}")
    missing = [n for n in (KT_J, D_J, TC_J) if n not in fit.names]
    if missing:
        raise ValueError(f"the {fit.method} fit has no {', '.join(missing)}: J, D and Tc need the "
                         f"motor model's Kt/J, D/J and Tc/J")
    ix = [fit.names.index(n) for n in (KT_J, D_J, TC_J)]
    # (b2, D/J, Tc/J) -> (1, D/J, Tc/J)/b2 is the torque side's map to the accel names
    # (its own inverse)
    values, cov = own_to_accel_names("torque", [fit.values[i] for i in ix], np.ones(3),
                                     np.asarray(fit.covariance)[np.ix_(ix, ix)])
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    return {name: (float(k * v), float(k * s)) for name, v, s in zip(("J", "D", "Tc"), values, std)}
