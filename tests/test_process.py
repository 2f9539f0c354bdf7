import cmath
import math

import numpy as np
import pytest

from autotuner.engine.plant.expression import parse_process
from autotuner.engine.plant.process import Process


def test_normalises_den_and_strips_leading_zeros():
    p = Process.from_tf([0, 0, 3], [0, 2, 4], 0.5, text="3/(2s+4)")
    assert p.num == (1.5,)
    assert p.den == (1.0, 2.0)
    assert p.delay == 0.5
    assert p.order == 1


@pytest.mark.parametrize(
    "num, den, delay, words",
    [
        ([1, 0, 0], [1, 1], 0.0, "improper"),
        ([1], [0, 0], 0.0, "denominator polynomial is zero"),
        ([1], [], 0.0, "empty"),
        ([math.nan], [1, 1], 0.0, "finite"),
        ([1], [1, math.inf], 0.0, "finite"),
        ([1], [1, 1], -0.1, "dead time"),
        ([1], [1, 1], math.inf, "dead time"),
    ],
)
def test_invalid_models_raise_clear_value_error(num, den, delay, words):
    with pytest.raises(ValueError, match=words):
        Process.from_tf(num, den, delay)


def test_freqresp_matches_factored_formula_including_delay():
    p = parse_process("1.5*exp(-0.7*s)/(4*s+1)^2")
    w = np.array([0.01, 0.3, 1.0, 10.0])
    expected = [1.5 * cmath.exp(-0.7j * x) / (4j * x + 1) ** 2 for x in w]
    np.testing.assert_allclose(p.freqresp(w), expected, rtol=1e-13)
    assert complex(p.freqresp(0.3)) == pytest.approx(expected[1], rel=1e-13)


def test_freqresp_integrating_and_nonminimum_phase():
    p = parse_process("exp(-0.5*s)/(s*(3*s+1))")
    w = 0.4
    expected = cmath.exp(-0.5j * w) / (1j * w * (3j * w + 1))
    assert complex(p.freqresp(w)) == pytest.approx(expected, rel=1e-13)
    q = parse_process("(1-0.6*s)/(2*s+1)^3")
    expected = (1 - 0.6j * w) / (2j * w + 1) ** 3
    assert complex(q.freqresp(w)) == pytest.approx(expected, rel=1e-13)


def test_poles_and_zeros():
    p = parse_process("(1-0.6*s)/((2*s+1)*(s+3))")
    np.testing.assert_allclose(sorted(p.poles.real), [-3, -0.5], rtol=1e-12)
    np.testing.assert_allclose(p.zeros, [1 / 0.6], rtol=1e-12)
    assert parse_process("2").poles.size == 0
    assert parse_process("1/(s+1)").zeros.size == 0


@pytest.mark.parametrize(
    "text, integrators, integrating, unstable, gain",
    [
        ("1.5*exp(-0.7*s)/(4*s+1)^2", 0, False, False, 1.5),
        ("(1-0.6*s)/(2*s+1)^3", 0, False, False, 1.0),
        ("exp(-0.5*s)/(s*(3*s+1))", 1, True, False, math.inf),
        ("-2/(s^2*(s+1))", 2, True, False, -math.inf),
        ("exp(-0.2*s)/(2*s-1)", 0, False, True, -1.0),
        ("1/(s^2-2*s+5)", 0, False, True, 0.2),  # poles 1 ± 2j
        ("1/(s^2+0.1*s+4)", 0, False, False, 0.25),
        ("1/(s+1)^8", 0, False, False, 1.0),  # repeated poles: np.roots is inexact
        ("1/(s^2+1)", 0, False, False, 1.0),  # marginally stable, not unstable
        ("s/(s*(s+1))", 0, False, False, 1.0),  # cancelled origin pole
        ("s/(s+1)", 0, False, False, 0.0),
        ("3", 0, False, False, 3.0),
        ("exp(-s)/(1000*s+1)", 0, False, False, 1.0),
    ],
)
def test_classification_and_static_gain(text, integrators, integrating, unstable, gain):
    p = parse_process(text)
    assert p.integrator_count == integrators
    assert p.is_integrating is integrating
    assert p.is_unstable is unstable
    assert p.static_gain() == pytest.approx(gain, rel=1e-12)


def test_static_gain_equals_freqresp_near_zero():
    p = parse_process("0.8*exp(-1.2*s)/((6*s+1)*(s+1))")
    assert p.static_gain() == pytest.approx(complex(p.freqresp(1e-9)).real, rel=1e-8)


@pytest.mark.parametrize(
    "text",
    [
        "1.5*exp(-0.7*s)/(4*s+1)^2",
        "(1-0.6*s)/(2*s+1)^3",
        "exp(-0.5*s)/(s*(3*s+1))",
        "-2*exp(-0.2*s)/(2*s-1)",
        "(s+1)/(s+2)",
        "3",
        "exp(-1e-05*s)/(1000*s+1)",
    ],
)
def test_str_is_readable_and_parses_back(text):
    p = parse_process(text)
    q = parse_process(str(p))
    np.testing.assert_allclose(q.num, p.num, rtol=1e-11)
    np.testing.assert_allclose(q.den, p.den, rtol=1e-11)
    assert q.delay == pytest.approx(p.delay, rel=1e-11)


def test_str_form():
    assert str(parse_process("1.5*exp(-0.7*s)/(4*s+1)^2")) == "0.09375*exp(-0.7*s)/(s^2+0.5*s+0.0625)"
    assert str(parse_process("(1-s)/(s+2)")) == "(-s+1)/(s+2)"
    assert str(parse_process("exp(-2*s)/s")) == "exp(-2*s)/(s)"
