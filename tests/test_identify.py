"""Step-response identification and exact frequency points against closed forms."""

import math

import pytest

from autotuner.engine.plant.expression import parse_process
from autotuner.engine.design.process_data import exact_point, from_fopdt, from_plant


def test_tangent_of_four_equal_lags():
    # 1/(s+1)^4: inflection at t = 3, slope 3³e⁻³/3!, y(3) = 1 − e⁻³(1 + 3 + 9/2 + 27/6).
    data = from_plant(parse_process("1/(s+1)^4"))
    r = 27 * math.exp(-3) / 6
    y3 = 1 - math.exp(-3) * (1 + 3 + 4.5 + 4.5)
    assert data.tangent.r == pytest.approx(r, rel=1e-5)
    assert data.tangent.d == pytest.approx(3 - y3 / r, rel=1e-4)


def test_tangent_of_integrating_process_is_the_asymptote():
    # e^{-0.5 s}/(s(3s+1)): y → t − 3.5 for large t.
    tangent = from_plant(parse_process("exp(-0.5*s)/(s*(3*s+1))")).tangent
    assert tangent.r == pytest.approx(1.0, rel=1e-4)
    assert tangent.d == pytest.approx(3.5, rel=1e-4)
    assert tangent.t63 is None


def test_least_squares_fit_recovers_an_fopdt_plant():
    fit = from_plant(parse_process("2*exp(-1.5*s)/(7*s+1)")).fopdt
    assert (fit.k, fit.t, fit.l) == pytest.approx((2.0, 7.0, 1.5), rel=1e-6)


def test_exact_ultimate_point():
    # 1/(s+1)^4: 45° per lag at ω = 1, |F| = 1/4.
    point = exact_point(parse_process("1/(s+1)^4"), 180.0)
    assert point.omega == pytest.approx(1.0, rel=1e-12)
    assert point.gain == pytest.approx(0.25, rel=1e-12)
    assert exact_point(parse_process("1/(s+1)^2"), 180.0) is None


def test_fopdt_data_is_exact():
    data = from_fopdt(2.0, 10.0, 2.0)
    assert (data.tangent.d, data.tangent.r, data.tangent.t63) == (2.0, 0.2, 12.0)
    assert data.tangent.a == pytest.approx(0.4)
