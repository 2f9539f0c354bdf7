"""Controller forms (methods.md §3.1): formulas, round trips, refusals."""

import cmath
import json
import math

import pytest
from hypothesis import given, strategies as st

from autotuner.engine.control.gains import (
    FormError,
    Gains,
    ParallelGains,
    SeriesGains,
    from_parallel,
    from_series,
    to_parallel,
    to_series,
)

gain = st.floats(min_value=1e-3, max_value=1e3) | st.floats(min_value=-1e3, max_value=-1e-3)
time = st.floats(min_value=1e-2, max_value=1e3)


def standard_tf(g: Gains, s: complex) -> complex:
    """Ideal (unfiltered) standard PID, error-to-output, b = c = 1."""
    integral = 0.0 if math.isinf(g.ti) else 1.0 / (g.ti * s)
    return g.k * (1.0 + integral + g.td * s)


def series_tf(sg: SeriesGains, s: complex) -> complex:
    integral = 0.0 if math.isinf(sg.ti) else 1.0 / (sg.ti * s)
    return sg.k * (1.0 + integral) * (1.0 + sg.td * s)


# -- hand-computed numbers ------------------------------------------------


def test_series_to_standard_hand_numbers():
    # K' = 2, Ti' = 3, Td' = 1: K = 2·4/3, Ti = 4, Td = 3/4.
    g = from_series(SeriesGains(k=2.0, ti=3.0, td=1.0))
    assert g.k == pytest.approx(8.0 / 3.0)
    assert g.ti == pytest.approx(4.0)
    assert g.td == pytest.approx(0.75)
    assert (g.nd, g.b, g.c) == (10.0, 1.0, 0.0)


def test_standard_to_series_hand_numbers():
    # Ti = 10, Td = 1.6: sqrt(1 − 0.64) = 0.6.
    sg = to_series(Gains(k=5.0, ti=10.0, td=1.6))
    assert sg.k == pytest.approx(5.0 / 2 * 1.6)  # 4.0
    assert sg.ti == pytest.approx(8.0)
    assert sg.td == pytest.approx(2.0)


def test_standard_to_series_boundary_ti_equals_4td():
    sg = to_series(Gains(k=1.0, ti=4.0, td=1.0))
    assert (sg.k, sg.ti, sg.td) == pytest.approx((0.5, 2.0, 2.0))
    # and back (Ti' = Td' lands on Ti = 4·Td, possibly a rounding hair off)
    assert to_series(from_series(SeriesGains(k=0.3, ti=0.7, td=0.7))).ti == pytest.approx(0.7)


def test_standard_to_parallel_hand_numbers():
    p = to_parallel(Gains(k=2.0, ti=4.0, td=0.5, nd=8.0))
    assert (p.kp, p.ki, p.kd) == pytest.approx((2.0, 0.5, 1.0))
    g = from_parallel(ParallelGains(kp=2.0, ki=0.5, kd=1.0), nd=8.0, b=0.7, c=0.2)
    assert (g.k, g.ti, g.td, g.nd, g.b, g.c) == pytest.approx((2.0, 4.0, 0.5, 8.0, 0.7, 0.2))


def test_parallel_derivative_filter_matches_standard():
    # Kd''/(N K'') must equal the standard filter time constant Td/N.
    g = Gains(k=3.0, ti=5.0, td=2.0, nd=7.0)
    p = to_parallel(g)
    assert p.kd / (g.nd * p.kp) == pytest.approx(g.td / g.nd)


def test_refuses_ti_below_4td_with_message():
    with pytest.raises(FormError) as ei:
        to_series(Gains(k=1.0, ti=3.0, td=1.0))
    msg = str(ei.value)
    assert "Ti ≥ 4·Td" in msg and "Ti = 3 s" in msg and "Td = 1 s" in msg
    assert isinstance(ei.value, ValueError)


def test_no_integral_conversions():
    g = Gains(k=2.0, td=0.5)
    assert to_series(g) == SeriesGains(k=2.0, ti=math.inf, td=0.5)
    assert from_series(SeriesGains(k=2.0, td=0.5)) == Gains(k=2.0, td=0.5)
    p = to_parallel(g)
    assert p.ki == 0.0
    assert from_parallel(p) == g


# -- properties ---------------------------------------------------------


@given(k=gain, ti=time, td=time)
def test_series_standard_round_trip(k, ti, td):
    # the conversion back picks the representation with Ti' >= Td'
    ti, td = max(ti, td), min(ti, td)
    sg = SeriesGains(k=k, ti=ti, td=td)
    back = to_series(from_series(sg))
    assert back.k == pytest.approx(k, rel=1e-6)
    assert back.ti == pytest.approx(ti, rel=1e-6)
    assert back.td == pytest.approx(td, rel=1e-6, abs=1e-9 * ti)


@given(k=gain, ti=time, ratio=st.floats(min_value=0.0, max_value=0.25))
def test_standard_series_round_trip_and_same_transfer_function(k, ti, ratio):
    g = Gains(k=k, ti=ti, td=ratio * ti)
    sg = to_series(g)
    assert sg.ti >= sg.td
    back = from_series(sg)
    assert back.k == pytest.approx(k, rel=1e-9)
    assert back.ti == pytest.approx(ti, rel=1e-9)
    assert back.td == pytest.approx(g.td, rel=1e-9, abs=1e-12 * ti)
    for w in (0.01 / ti, 1.0 / ti, 100.0 / ti):
        s = 1j * w
        assert cmath.isclose(series_tf(sg, s), standard_tf(g, s), rel_tol=1e-9)


@given(k=gain, ti=time, td=time)
def test_series_with_td_above_ti_is_still_the_same_controller(k, ti, td):
    sg = SeriesGains(k=k, ti=ti, td=td)
    g = from_series(sg)
    assert g.ti >= 4 * g.td * (1 - 1e-12)
    for w in (0.1 / ti, 1.0 / ti, 10.0 / ti):
        assert cmath.isclose(standard_tf(g, 1j * w), series_tf(sg, 1j * w), rel_tol=1e-9)


@given(
    k=gain,
    ti=time | st.just(math.inf),
    td=st.floats(min_value=0.0, max_value=1e3),
    nd=st.floats(min_value=1.0, max_value=30.0),
    b=st.floats(min_value=0.0, max_value=1.0),
    c=st.floats(min_value=0.0, max_value=1.0),
)
def test_standard_parallel_round_trip(k, ti, td, nd, b, c):
    g = Gains(k=k, ti=ti, td=td, nd=nd, b=b, c=c)
    back = from_parallel(to_parallel(g), nd=nd, b=b, c=c)
    assert back.k == g.k
    assert back.ti == pytest.approx(g.ti, rel=1e-12)
    assert back.td == pytest.approx(g.td, rel=1e-12)
    assert (back.nd, back.b, back.c) == (nd, b, c)


@given(kp=gain, ti=time, td=st.floats(min_value=0.0, max_value=1e3))
def test_parallel_standard_round_trip(kp, ti, td):
    p = ParallelGains(kp=kp, ki=kp / ti, kd=kp * td)
    back = to_parallel(from_parallel(p))
    assert back.kp == p.kp
    assert back.ki == pytest.approx(p.ki, rel=1e-12)
    assert back.kd == pytest.approx(p.kd, rel=1e-12)


# -- Gains itself ---------------------------------------------------------


def test_controller_type_and_ki():
    assert Gains(k=1.0).controller_type == "P"
    assert Gains(k=1.0, ti=2.0).controller_type == "PI"
    assert Gains(k=1.0, td=2.0).controller_type == "PD"
    assert Gains(k=1.0, ti=2.0, td=0.1).controller_type == "PID"
    assert Gains(k=3.0, ti=2.0).ki == 1.5
    assert Gains(k=3.0).ki == 0.0


def test_as_json_keys_and_null_ti():
    d = Gains(k=0.61, ti=5.2).as_json()
    assert d == {"pk": 0.61, "pti": 5.2, "ptd": 0.0, "pnd": 10.0, "pb": 1.0, "pc": 0.0}
    d = Gains(k=2.0, td=1.0).as_json()
    assert d["pti"] is None
    assert json.loads(json.dumps(d))["pti"] is None  # valid JSON, no Infinity
    assert Gains.from_json(d) == Gains(k=2.0, td=1.0)


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"k": 0.0}, "k"),
        ({"k": math.nan}, "k"),
        ({"k": math.inf}, "k"),
        ({"k": 1.0, "ti": 0.0}, "ti"),
        ({"k": 1.0, "ti": -1.0}, "ti"),
        ({"k": 1.0, "ti": math.nan}, "ti"),
        ({"k": 1.0, "td": -0.1}, "td"),
        ({"k": 1.0, "td": math.inf}, "td"),
        ({"k": 1.0, "nd": 0.0}, "nd"),
        ({"k": 1.0, "nd": math.nan}, "nd"),
        ({"k": 1.0, "b": math.nan}, "b"),
        ({"k": 1.0, "c": math.inf}, "c"),
        ({"k": True}, "k"),
    ],
)
def test_gains_validation_names_parameter(kwargs, name):
    with pytest.raises(ValueError, match=rf"^{name} must"):
        Gains(**kwargs)


def test_other_forms_validate():
    with pytest.raises(ValueError, match="^ti must"):
        SeriesGains(k=1.0, ti=0.0)
    with pytest.raises(ValueError, match="^kp must"):
        ParallelGains(kp=0.0)
    with pytest.raises(ValueError, match="ki must have the sign of kp"):
        ParallelGains(kp=1.0, ki=-0.1)
    with pytest.raises(ValueError, match="kd must have the sign of kp"):
        ParallelGains(kp=-1.0, kd=0.1)
