"""Property-based fuzz of the REST API from its own OpenAPI description (schemathesis 4, in-process ASGI).

Schemathesis reads the description the app serves (``/api/v1/openapi.json``,
here ``app.openapi()``) and generates, for every operation, valid and invalid
requests: its coverage phase (boundary values, wrong types, missing and extra
fields, unsupported methods, missing auth) then a bounded random phase. No
network: requests go to the ASGI app in this process, whose lifespan (the
loop manager, the simulated plants) runs in schemathesis' transport.

Every response must hold to the properties of issue 6:

* no server error (5xx);
* no Python traceback anywhere in a response;
* a response that conforms to the description: a documented status code, the
  declared content type, a body valid against the declared schema;
* no state change from a refused request (4xx): per loop, no new session, no
  new history record, an idle loop's outcome and gains unchanged, and a busy
  loop either still busy or ended by itself (never with code ABORTED, which
  only an accepted TBRK gives).

Three runs. With an operator token, writes may start (202) and abort sessions.
Without a token and with a viewer token, every write must be refused and
nothing may change. And the stateful phase: schemathesis chains operations
along the links it infers (a loop listed, then tuned, broken, applied, its
history read), with the operator token.

In every phase a request the schema allows (schemathesis' positive data)
may be refused only for a reason the client could have read first: the
loop's state (409 busy, idle, nothing_to_apply, ...), or a TUNE's ``amp`` or
``hysteresis`` above the loop's own bound, which a static schema cannot
carry per loop and the loop's status publishes (``bounds``). Any other 422
for schema-valid data is a failure (it was: ``amp`` 5.7e307 was valid).

The loops are simulated plants in real time (speed 1), so
a session the fuzzer starts runs far longer than the run unless its settings
make it fail at once.

The description cannot know a deployment's loop ids, so the fuzzed copy
narrows ``loop_id`` to an enum of the configured loops: valid requests reach
real loops (TUNE, TBRK, 409 busy/idle/group_busy) and negative ones (any
other string) the 404s. Nothing else is changed.
"""

from __future__ import annotations

import copy
import time
from typing import Any

import pytest
import schemathesis
from hypothesis import HealthCheck, settings
from schemathesis.checks import not_a_server_error
from schemathesis.python import asgi
from schemathesis.specs.openapi.checks import content_type_conformance, response_schema_conformance

from api.app import PREFIX, create_app
from api.auth import token_hash
from autotuner.service.config import DaemonConfig, Token
from autotuner.engine.outcome import Code

OPERATOR, VIEWER = "fuzz-operator", "fuzz-viewer"
LOOP_IDS = ("TIC-1", "LIC-2", "FIC-3")
# Random examples per operation after the coverage phase; the whole file stays well under a minute.
EXAMPLES = 25
# Scenarios of the stateful phase (each up to 6 linked calls).
STATEFUL_EXAMPLES = 20
# A Server-Sent Events stream never ends; the transport keeps what arrived within this many seconds.
STREAM_TIMEOUT = 0.5
WRITES = frozenset({"POST", "PUT", "PATCH", "DELETE"})
# A body that is not JSON at all is refused by FastAPI with 400 {"code": "bad_request"} before
# validation, and before the auth dependency runs.
BAD_BODY = 400

CONFIG = DaemonConfig.model_validate({
    "history": ":memory:",
    "tokens": [Token(name="hmi", role="viewer", sha256=token_hash(VIEWER)).model_dump()],
    "loops": [
        {"id": "TIC-1", "sim": {"plant": "1.5*exp(-0.7*s)/(4*s+1)^2"}, "ts": 0.5, "speed": 1.0,
         "tuning": {"amp": 5.0}, "limits": {"pv": [0.0, 100.0], "mv": [0.0, 100.0]}},
        {"id": "LIC-2", "sim": {"plant": "0.2*exp(-1*s)/(s*(2*s+1))"}, "ts": 0.5, "speed": 1.0,
         "tuning": {"amp": 5.0}, "group": "tank"},
        {"id": "FIC-3", "sim": {"plant": "2*exp(-0.5*s)/((20*s+1)*(2*s+1))"}, "ts": 0.5, "speed": 1.0,
         "tuning": {"amp": 5.0}, "group": "tank"},
    ],
})


def _narrowed(spec: dict[str, Any]) -> dict[str, Any]:
    """The app's description with the ``loop_id`` path parameter narrowed to the configured loops."""
    spec = copy.deepcopy(spec)
    for methods in spec["paths"].values():
        for operation in methods.values():
            for parameter in operation.get("parameters", []):
                if parameter["name"] == "loop_id" and parameter["in"] == "path":
                    parameter["schema"]["enum"] = list(LOOP_IDS)
    return spec


APP = create_app(CONFIG, env_token=OPERATOR)
SPEC = _narrowed(APP.openapi())
schema = schemathesis.openapi.from_dict(SPEC)
schema.app = APP  # requests go to the app in-process; its lifespan starts with the first request


@pytest.fixture(scope="module", autouse=True)
def _lifespan():
    """Stop the app after the module: abort the fuzzer's sessions, restore their loops, stop the plants."""
    yield
    asgi.shutdown_lifespans()


def _bearer(token: str | None) -> dict[str, str]:
    return {} if token is None else {"Authorization": f"Bearer {token}"}


def _read(path: str) -> Any:
    """GET ``/api/v1`` + ``path`` with the viewer token, in-process (a plain client: cheaper than a Case)."""
    with asgi.get_client(APP) as client:
        r = client.get(PREFIX + path, headers=_bearer(VIEWER))
    assert r.status_code == 200, (path, r.status_code, r.text)
    return r.json()


def _state() -> dict[str, dict[str, Any]]:
    """The loops' observable state: GET /loops, by id."""
    return {loop["id"]: loop for loop in _read("/loops")}


def _assert_unchanged(case, before: dict[str, dict[str, Any]], what: str) -> None:
    """A refused request changed nothing; a running session may only have ended by itself."""
    after = _state()
    assert before.keys() == after.keys()
    for loop_id, b in before.items():
        a = after[loop_id]
        assert a["session"] == b["session"], f"{what}: a session started on {loop_id}"
        if not b["tbsy"]:
            keys = ("tbsy", "te", "ite", "message", "gains", "point")
            assert {k: a[k] for k in keys} == {k: b[k] for k in keys}, f"{what}: idle {loop_id} changed"
        elif not a["tbsy"]:
            assert a["ite"] != Code.ABORTED, f"{what}: the session on {loop_id} was aborted"
    loop_id = case.path_parameters.get("loop_id") if case.path_parameters else None
    if case.method in WRITES and loop_id in before:  # and nothing recorded: the newest session is the same
        newest = _read(f"/loops/{loop_id}/history?limit=1")
        assert (newest[0]["id"] if newest else None) == before[loop_id]["session"], f"{what}: history grew"


def _settle(case, response) -> None:
    """After an accepted TBRK: until its loop is idle again (the abort and the restore are asynchronous)."""
    if not (case.path.endswith("/break") and response.status_code == 202):
        return
    loop_id = case.path_parameters["loop_id"]
    deadline = time.monotonic() + 10.0
    while _read(f"/loops/{loop_id}")["tbsy"]:
        assert time.monotonic() < deadline, f"{loop_id} still busy 10 s after TBRK"
        time.sleep(0.02)


def _documented(case, response) -> None:
    """The status is one the description declares for the operation (405 for a method it does not have)."""
    operations = SPEC["paths"].get(case.path, {})
    status = response.status_code
    if case.method.lower() not in operations:
        assert status == 405, f"{case.method} {case.path}: {status} for an undeclared method"
        return
    operation = operations[case.method.lower()]
    declared = {int(code) for code in operation["responses"]}
    assert status in declared, f"{case.method} {case.formatted_path}: {status} not in {sorted(declared)}"


def _no_traceback(response) -> None:
    text = response.text
    assert "Traceback" not in text and 'File "/' not in text, f"traceback in the response: {text[:500]}"


@schemathesis.check
def refusals_explained(ctx, response, case) -> None:
    """Schema-valid data refused as invalid (422) only for a bound the loop's status publishes."""
    if response.status_code != 422 or case.meta is None or not case.meta.generation.mode.is_positive:
        return
    loop_id = (case.path_parameters or {}).get("loop_id")
    body = case.body if isinstance(case.body, dict) else {}
    assert case.path.endswith("/tune") and loop_id in LOOP_IDS, f"valid data refused: {response.text}"
    bounds = _read(f"/loops/{loop_id}")["bounds"]
    over = [name for name in ("amp", "hysteresis") if isinstance(body.get(name), int | float)
            and body[name] > bounds[name]]
    message = response.json()["message"]
    assert over and message.startswith(f"{over[0]}: ") and f"bounds.{over[0]}" in message, \
        f"{body} refused, within the loop's published bounds {bounds}: {message}"


CHECKS = [not_a_server_error, content_type_conformance, response_schema_conformance, refusals_explained]


def _transport(case) -> dict[str, Any]:
    return {"timeout": STREAM_TIMEOUT} if case.path.endswith("/events") else {}


def _call(case, token: str | None):
    """The request, with the built-in checks (no 5xx, content type, body schema) and ours."""
    response = case.call_and_validate(headers=_bearer(token), checks=CHECKS, **_transport(case))
    _no_traceback(response)
    _documented(case, response)
    return response


FUZZ = settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck))


@schema.parametrize()
@FUZZ
def test_operator_fuzz(case):
    before = _state()
    response = _call(case, OPERATOR)
    what = f"{case.method} {case.formatted_path} -> {response.status_code}"
    if 400 <= response.status_code < 500:
        _assert_unchanged(case, before, what)
    else:
        _settle(case, response)


@schema.parametrize()
@FUZZ
def test_writes_without_operator_are_refused(case):
    for token in (None, VIEWER):
        before = _state()
        response = _call(case, token)
        what = f"{case.method} {case.formatted_path} with {'no token' if token is None else 'viewer token'}"
        if case.method in WRITES:
            assert 400 <= response.status_code < 500, f"{what}: {response.status_code}"
            if response.status_code not in (401, 403):
                # Only a request refused for itself before auth is looked at: a body that is not
                # JSON (FastAPI parses the body before running the auth dependency), a request
                # FastAPI cannot even validate (422), or a method the path does not have. Either
                # way it is refused and nothing changes (checked below).
                assert response.status_code in (BAD_BODY, 405, 422), f"{what}: {response.status_code}"
        elif token is None and case.method.lower() in SPEC["paths"][case.path] and not case.path.endswith("/health"):
            assert response.status_code == 401, f"{what}: {response.status_code}"
        _assert_unchanged(case, before, f"{what} -> {response.status_code}")


class _Workflow(schema.as_state_machine()):
    """The stateful phase: chains of operations along the inferred links, with the operator token and our checks."""

    def get_call_kwargs(self, case) -> dict[str, Any]:
        return {"headers": _bearer(OPERATOR), **_transport(case)}

    def validate_response(self, response, case, additional_checks=None, **kwargs) -> None:
        case.validate_response(response, checks=CHECKS, transport_kwargs=kwargs)
        _no_traceback(response)
        _documented(case, response)
        if case.path.endswith("/break") and response.status_code == 202:
            _settle(case, response)


TestStateful = _Workflow.TestCase
TestStateful.settings = settings(max_examples=STATEFUL_EXAMPLES, stateful_step_count=6, deadline=None,
                                 suppress_health_check=list(HealthCheck))
