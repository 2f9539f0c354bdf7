"""The result's types: the engine's dataclasses say what each field is, and the API's response models
(pydantic, only at the boundary) have exactly the keys the engine's one encoder gives."""

from __future__ import annotations

import dataclasses
import json
import typing

import numpy as np

import pytest
from pydantic import TypeAdapter

from api.models import LoopStatus, SessionSummary
from autotuner.engine.design.point_design import Design, design
from autotuner.engine.design.process_data import exact_point
from autotuner.engine.experiment.relay import Identification
from autotuner.engine.outcome import Code
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.result import (DesignRecord, ExperimentRecord, GainsRecord, PointRecord, ResultRecord, Trace,
                                     TuneResult)


def _result() -> TuneResult:
    """A successful result on the exact 135° point (no experiment needed)."""
    point = exact_point(parse_process("exp(-s)/(2*s+1)"), 135.0)
    ident = Identification(point=point, static_gain=1.0, duration=70.0, periods=7.0, samples=700, hysteresis=0.0,
                           noise_std=0.0)
    t = np.arange(3.0)
    return TuneResult(Code.OK, "ok", "PI", ident, design(point, 1.0, "PI", 1.4), Trace(t, t, t))


RECORDS = (ResultRecord, PointRecord, GainsRecord, DesignRecord, ExperimentRecord)


def test_every_field_of_the_result_says_what_it_is() -> None:
    for cls in (TuneResult, Trace, Identification, Design, *RECORDS):
        for f in dataclasses.fields(cls):
            assert f.metadata.get("description"), f"{cls.__name__}.{f.name} has no description"


def test_the_record_round_trips_through_its_json() -> None:
    result = _result()
    doc = json.loads(json.dumps(result.as_json(), allow_nan=False))
    record = ResultRecord.from_json(doc)
    assert record == result.record() and record.to_json() == doc
    # What the design computed, read back from the record: the point as a complex F(jω₀), the gains.
    assert abs(record.point.point().value - result.identification.point.value) < 1e-12
    assert record.gains.gains() == result.design.gains and record.code is Code.OK
    assert parse_process(record.design.model).delay == pytest.approx(result.design.model.delay)


def test_a_row_stored_before_the_design_key_decodes_with_it_null() -> None:
    doc = _result().as_json()
    old = {k: v for k, v in doc.items() if k not in ("design", "forms")}
    record = ResultRecord.from_json(old)
    assert record.design is None and record.forms is None and record.gains == GainsRecord(**doc["gains"])
    with pytest.raises(ValueError, match="experiment"):
        ResultRecord.from_json({k: v for k, v in doc.items() if k != "experiment"})


def test_the_api_models_are_the_engine_records() -> None:
    doc = json.loads(json.dumps(_result().as_json(), allow_nan=False))
    # The loop status and the session carry the result's point and gains as the engine's records, and pydantic
    # reads their descriptions into the OpenAPI document.
    status = typing.get_type_hints(LoopStatus)
    assert status["point"] == PointRecord | None and status["gains"] == GainsRecord | None
    assert SessionSummary.model_fields["result"].annotation == ResultRecord | None
    schema = TypeAdapter(ResultRecord).json_schema()
    point = schema["$defs"]["PointRecord"]["properties"]["omega"]
    assert "rad/s" in point["description"] and point["examples"] == [0.4187]
    assert TypeAdapter(ResultRecord).dump_python(ResultRecord.from_json(doc), mode="json") == doc
    assert doc["forms"]["parallel"]["kp"] == doc["gains"]["pk"]
