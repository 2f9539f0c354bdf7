"""Variability: the standard deviation of the control error and the Harris index.

Harris (1989), "Assessment of control loop performance", Can. J. Chem. Eng. 67:856–861; Desborough and Harris
(1992), "Performance assessment measures for univariate feedback control", Can. J. Chem. Eng. 70:1186–1197. The
error of a loop under any controller is e = ψ(q⁻¹)a, a moving average of white noise a; the first b terms
(b: the process dead time in samples, counting the hold's sample) no controller can change, so the least
variance any controller could reach is σ²_mv = σ²_a·(ψ0² + … + ψ(b−1)²). ψ and σ²_a come from an AR model of
e (Yule–Walker). The index η = σ²_mv / σ²_e is 1 at minimum variance and near 0 far from it.

Without a model the dead time is taken as one sample: σ²_mv is then the smallest it can be, and η a lower bound.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg

AR_ORDER = 20  # the AR model's order (Desborough and Harris use 10–30)


def harris_index(e: np.ndarray, delay_samples: int) -> float | None:
    """η = σ²_mv / σ²_e of the error ``e`` for a dead time of ``delay_samples`` (≥ 1) samples (None: too few
    samples or no variance). The AR model comes from the Yule–Walker equations (the error's autocovariance, by
    FFT), the cheap way to the least-squares fit for a record this long."""
    x = e - e.mean()
    n = len(x)
    order = min(AR_ORDER, n // 20)
    if order < 2 or not np.any(x):
        return None
    size = 1 << (2 * n - 1).bit_length()
    spectrum = np.fft.rfft(x, size)
    r = np.fft.irfft(spectrum * np.conj(spectrum), size)[: order + 1] / n  # autocovariance, lags 0…order
    try:
        coef = scipy.linalg.solve_toeplitz(r[:order], r[1:])
    except np.linalg.LinAlgError:  # a singular autocovariance: a pure sinusoid, say
        return None
    residual = float(r[0] - coef @ r[1:])
    b = max(1, delay_samples)
    psi = np.zeros(b)  # impulse response of 1/A(q⁻¹): ψ_k = Σ_i coef_i ψ_(k-i)
    psi[0] = 1.0
    for k in range(1, b):
        m = min(k, order)
        psi[k] = float(coef[:m] @ psi[k - 1::-1][:m])
    return float(min(1.0, max(0.0, residual) * float(psi @ psi) / r[0]))


def delay_samples(model_delay: float | None, ts: float) -> int:
    """The dead time in samples for the Harris index: ⌊L/ts⌋ + 1 (the zero-order hold's sample), or 1 without
    a model.

    ``model_delay``: the model's dead time L, s (None: no model); ``ts``: the sample time, s.
    """
    return 1 if model_delay is None else int(math.floor(model_delay / ts + 1e-9)) + 1
