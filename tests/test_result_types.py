"""The result's types: the engine's dataclasses say what each field is, and the API's response models
(pydantic, only at the boundary) have exactly the keys the engine's one encoder gives."""

from __future__ import annotations

import dataclasses
import json

import numpy as np

from api.models import GainsOut, LoopStatus, Point
from autotuner.engine.design.point_design import design
from autotuner.engine.design.process_data import exact_point
from autotuner.engine.experiment.relay import Identification
from autotuner.engine.outcome import Code
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.simulated_tuning import Trace, TuneResult


def _result() -> TuneResult:
    """A successful result on the exact 135° point (no experiment needed)."""
    point = exact_point(parse_process("exp(-s)/(2*s+1)"), 135.0)
    ident = Identification(point=point, static_gain=1.0, duration=70.0, periods=7.0, samples=700, hysteresis=0.0,
                           noise_std=0.0)
    t = np.arange(3.0)
    return TuneResult(Code.OK, "ok", "PI", ident, design(point, 1.0, "PI", 1.4), Trace(t, t, t))


def test_every_field_of_the_result_says_what_it_is() -> None:
    for cls in (TuneResult, Trace):
        for f in dataclasses.fields(cls):
            assert f.metadata.get("description"), f"{cls.__name__}.{f.name} has no description"


def test_the_api_models_have_the_keys_the_engine_encodes() -> None:
    doc = json.loads(json.dumps(_result().as_json(), allow_nan=False))
    assert set(Point.model_fields) == set(doc["point"])
    assert set(GainsOut.model_fields) == set(doc["gains"])
    Point.model_validate(doc["point"])
    GainsOut.model_validate(doc["gains"])
    # The loop status carries the result's controller, point, static gain and gains as they are.
    assert {"controller", "point", "static_gain", "gains"} <= set(LoopStatus.model_fields)
    assert doc["forms"]["parallel"]["kp"] == doc["gains"]["pk"]
    assert set(doc["design"]) >= {"model", "ms_model", "notes"}
