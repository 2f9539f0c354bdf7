import csv
import math
from pathlib import Path

import numpy as np
import pytest

from autotuner.engine.plant.expression import ExpressionError, parse_process

BENCH = Path("/work/shared/bench/amigo-batch.csv")


def coeffs_close(actual, expected, rel=1e-12):
    return len(actual) == len(expected) and np.allclose(actual, expected, rtol=rel, atol=0)


@pytest.mark.parametrize(
    "text, num, den, delay",
    [
        # 1.5/(16 s^2 + 8 s + 1), normalised by 16
        ("1.5*exp(-0.7*s)/(4*s+1)^2", [1.5 / 16], [1, 0.5, 1 / 16], 0.7),
        # (1-0.6s)/(8 s^3 + 12 s^2 + 6 s + 1)
        ("(1-0.6*s)/(2*s+1)^3", [-0.6 / 8, 1 / 8], [1, 12 / 8, 6 / 8, 1 / 8], 0.0),
        # 0.8/(6 s^2 + 7 s + 1)
        ("0.8*exp(-1.2*s)/((6*s+1)*(s+1))", [0.8 / 6], [1, 7 / 6, 1 / 6], 1.2),
        ("exp(-0.5*s)/(s*(3*s+1))", [1 / 3], [1, 1 / 3, 0], 0.5),
        ("exp(-0.2*s)/(2*s-1)", [0.5], [1, -0.5], 0.2),
        # (s+1)(0.25 s^2 + 0.7 s + 1) = 0.25 s^3 + 0.95 s^2 + 1.7 s + 1
        ("1/((s+1)*((0.5*s)^2+1.4*0.5*s+1))", [4], [1, 3.8, 6.8, 4], 0.0),
        ("exp(-s)", [1], [1], 1.0),
        ("exp(-s*0.5)/(s+1)", [1], [1, 1], 0.5),
        ("exp(-(0.2+0.3)*s)/(s+1)", [1], [1, 1], 0.5),
        ("exp(-0.3*s)*exp(-0.4*s)/(s+1)", [1], [1, 1], 0.7),
        ("2.5", [2.5], [1], 0.0),
        ("-2/(s+1)", [-2], [1, 1], 0.0),
        ("+2/(-s+1)", [-2], [1, -1], 0.0),
        ("1/(s+1) + 1/(s+2)", [2, 3], [1, 3, 2], 0.0),
        ("1/(s+1) - 1/(s+2)", [1], [1, 3, 2], 0.0),
        ("exp(-s)/(s+1) + exp(-s)/(s+2)", [2, 3], [1, 3, 2], 1.0),
        ("(s+1)/(s+2)", [1, 1], [1, 2], 0.0),
        ("((s+1)-s)/(s+2)", [1], [1, 2], 0.0),
        ("1/(2e-3*s+1)", [500], [1, 500], 0.0),
        ("1/(.5*s+1E1)", [2], [1, 20], 0.0),
        ("1/(1.*s+2.5e+1)", [1], [1, 25], 0.0),
        ("2^3/(s+1)^0", [8], [1], 0.0),
        ("1/(s+1)^2^1", [1], [1, 2, 1], 0.0),
        ("1/s/s", [1], [1, 0, 0], 0.0),
        ("  1 / ( s + 1 )  ", [1], [1, 1], 0.0),
    ],
)
def test_parses_to_expected_transfer_function(text, num, den, delay):
    p = parse_process(text)
    assert coeffs_close(p.num, num), p.num
    assert coeffs_close(p.den, den), p.den
    assert p.delay == pytest.approx(delay, rel=1e-12, abs=0)
    assert p.text == text.strip()


def test_caret_and_doublestar_powers_are_equivalent():
    for base in ["(4*s+1)", "(0.5*s+1)", "s"]:
        for k in range(5):
            a = parse_process(f"1/{base}^{k}")
            b = parse_process(f"1/{base}**{k}")
            assert a.num == b.num and a.den == b.den
    assert parse_process("2**3**2").num == (2.0**9,)  # right associative


def test_power_binds_tighter_than_unary_minus():
    assert parse_process("-2^2").num == (-4.0,)
    assert parse_process("(-2)^2").num == (4.0,)


@pytest.mark.parametrize(
    "text, position, token, words",
    [
        ("1/(s+1)**2x", 10, "x", "unexpected token 'x'"),
        ("2s", 1, "s", "implicit multiplication"),
        ("(2s+1)", 2, "s", "implicit multiplication"),
        ("2 (s+1)", 2, "(", "implicit multiplication"),
        ("", 0, "", "empty expression"),
        ("   ", 0, "", "empty expression"),
        ("(s+1", 0, "(", "unbalanced"),
        ("1/((s+1)*(s+2)", 2, "(", "unbalanced"),
        ("s+1)", 3, ")", "unbalanced"),
        ("()", 1, ")", "unexpected token ')'"),
        ("s+", 2, "", "unexpected end"),
        ("1/(s+1) 3", 8, "3", "unexpected token '3'"),
        ("x+1", 0, "x", "unknown identifier 'x'"),
        ("1/(T*s+1)", 3, "T", "unknown identifier 'T'"),
        ("sin(s)/(s+1)", 0, "sin", "unknown function 'sin'"),
        ("exp*2", 3, "*", "expected '('"),
        ("s#1", 1, "#", "invalid character '#'"),
        ("exp(+s)/(s+1)", 0, "exp(+s)", "positive exponent"),
        ("exp(0.5*s)", 0, "exp(0.5*s)", "time advance"),
        ("1/(s+1)*exp(-s^2)", 8, "exp(-s^2)", "-L*s"),
        ("exp(-s-1)", 0, "exp(-s-1)", "-L*s"),
        ("exp(1/s)", 0, "exp(1/s)", "-L*s"),
        ("exp(2)", 0, "exp(2)", "-L*s"),
        ("exp(exp(-s))", 0, "exp(exp(-s))", "-L*s"),
        ("1/exp(-s)", 0, "1/exp(-s)", "negative net dead time"),
        ("exp(-s)/(s+1) + 1/(s+1)", 14, "+", "different dead times"),
        ("1/0", 2, "0", "division by zero"),
        ("1/(s-s)", 2, "(s-s)", "division by zero"),
        ("s^2/(s+1)", 0, "s^2/(s+1)", "improper"),
        ("s", 0, "s", "improper"),
        ("1/(s+1)^2.5", 8, "2.5", "non-negative integer"),
        ("1/(s+1)^-1", 8, "-1", "non-negative integer"),
        ("1/(s+1)^s", 8, "s", "non-negative integer"),
        ("1/(s+1)^1000", 8, "1000", "too large"),
        ("1/(2e*s+1)", 3, "2e", "malformed number"),
        ("1/(2e-*s+1)", 3, "2e-", "malformed number"),
        ("1e999/(s+1)", 0, "1e999", "out of range"),
    ],
)
def test_errors_name_token_and_position(text, position, token, words):
    with pytest.raises(ExpressionError) as info:
        parse_process(text)
    err = info.value
    assert isinstance(err, ValueError)
    assert err.position == position
    assert err.token == token
    message = str(err)
    assert words in message
    assert f"at position {position} in {text!r}" in message
    # caret line points at the offending character
    assert message.splitlines()[-1] == "  " + " " * position + "^"


def test_bad_token_appears_quoted_in_message():
    with pytest.raises(ExpressionError, match=r"unexpected token 'x' at position 10 in '1/\(s\+1\)\*\*2x'"):
        parse_process("1/(s+1)**2x")


def load_bench():
    with BENCH.open(newline="") as f:
        return list(csv.DictReader(f))


def test_bench_file_has_all_rows():
    assert len(load_bench()) == 133


@pytest.mark.parametrize("row", load_bench(), ids=lambda r: r["id"])
def test_bench_expression_matches_tabulated_figures(row):
    p = parse_process(row["expr"])
    expected_gain = float(row["static_gain"])
    if math.isinf(expected_gain):
        assert p.is_integrating
        assert p.static_gain() == expected_gain
    else:
        assert p.static_gain() == pytest.approx(expected_gain, rel=1e-9)
    w135, k135 = float(row["w135"]), float(row["K135"])
    f = complex(p.freqresp(w135))
    assert abs(f) == pytest.approx(k135, rel=2e-5)
    # w135 is tabulated to 6 digits: allow the phase error that implies
    phase_deg = math.degrees(np.angle(f))
    assert (phase_deg + 135 + 180) % 360 - 180 == pytest.approx(0, abs=0.01)


def test_expression_error_survives_pickling():
    # The benchmark parses in worker processes, which send errors back pickled.
    import pickle

    with pytest.raises(ExpressionError) as info:
        parse_process("2s+1")
    copy = pickle.loads(pickle.dumps(info.value))
    assert str(copy) == str(info.value)
    assert (copy.position, copy.token) == (info.value.position, info.value.token)
