"""The closed-form references of physics/analytic.py against the series printed by Dimitriadis et al. (2002).

The bracket F / F_Hertz is a quartic in chi = sqrt(R d)/h; its coefficients are recovered exactly by a
polynomial fit through five or more points and compared with the printed ones to their printed digits.
"""

import numpy as np

from transtac_sim.physics.analytic import bonded_coefficients, layer_factor

CHI = np.array([0.05, 0.1, 0.2, 0.32, 0.5, 0.75, 1.0])


def _coefficients(factor) -> np.ndarray:
    """Coefficients c0..c4 of the quartic ``factor(chi)``."""
    return np.polynomial.polynomial.polyfit(CHI, factor(CHI), 4)


def _matches_printed(coefs: np.ndarray, printed: list[str]) -> bool:
    """c0 is 1 and c1..c4 round to the ``printed`` values at their printed number of decimals."""
    return abs(coefs[0] - 1.0) < 1e-9 and all(
        abs(c - float(p)) <= 0.5 * 10.0 ** -len(p.split(".")[1]) + 1e-12 for c, p in zip(coefs[1:], printed, strict=True))


def test_bonded_incompressible_series():
    """nu = 0.5, bonded: 1 + 1.133 chi + 1.283 chi^2 + 0.769 chi^3 - 0.0975 chi^4 (the paper prints the last
    term with a + sign; its general formula, checked on the non-bonded series below, gives -)."""
    a0, b0 = bonded_coefficients(0.5)
    assert (round(a0, 4), round(b0, 4)) == (-1.7795, 1.0079)
    coefs = _coefficients(lambda chi: layer_factor(a0, b0, chi))
    assert _matches_printed(coefs, ["1.133", "1.283", "0.769", "-0.0975"]), coefs
    series = 1 + 1.133 * CHI + 1.283 * CHI**2 + 0.769 * CHI**3 - 0.0975 * CHI**4
    rounding = 5e-4 * (CHI + CHI**2 + CHI**3) + 5e-5 * CHI**4  # half a unit of each printed digit
    assert np.all(np.abs(layer_factor(a0, b0, CHI) - series) <= rounding + 1e-12)
    # why -: the same bracket with the non-bonded coefficients alpha0 = -0.347 (3 - 2 nu)/(1 - nu),
    # beta0 = 0.056 (5 - 2 nu)/(1 - nu) gives the paper's 1 + 0.884 chi + 0.781 chi^2 + 0.386 chi^3 + 0.0048 chi^4
    # at nu = 0.5, signs included, so the sign of the chi^4 term is the formula's
    a0, b0 = -0.347 * 2 / 0.5, 0.056 * 4 / 0.5
    coefs = _coefficients(lambda chi: layer_factor(a0, b0, chi))
    assert _matches_printed(coefs, ["0.884", "0.781", "0.386", "0.0048"]), coefs

