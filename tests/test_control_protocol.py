"""The control socket's protocol v1 (runtime.control.protocol): what is accepted, and that every
malformed request is refused with a ProtocolError naming the field (its id echoed when the id
itself could be read)."""

from __future__ import annotations

import json
import math

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from runtime.control.protocol import (
    MAX_DEPTH,
    MAX_ID_CHARS,
    MAX_WAYPOINTS,
    ProtocolError,
    Request,
    Waypoint,
    encode,
    parse_request,
    reply,
)

V_MAX = 0.5  # the configured limits.v_max the tests pass as max_speed_limit


def parse(obj: object) -> Request:
    line = obj if isinstance(obj, bytes) else json.dumps(obj).encode()
    return parse_request(line, V_MAX)


def refused(obj: object) -> ProtocolError:
    with pytest.raises(ProtocolError) as info:
        parse(obj)
    return info.value


# --- accepted -------------------------------------------------------------------------------

def test_a_full_goal_is_accepted_with_every_field():
    req = parse({"v": 1, "id": "g1", "type": "goal", "x": 1.5, "y": -2, "tolerance": 0.2,
                 "max_speed": 0.3, "frame": "relative", "timeout": 60})
    assert req == Request("goal", "g1", (Waypoint(1.5, -2.0, 0.2, 0.3),), "relative", False,
                          60.0)
    assert isinstance(req.waypoints[0].y, float)


def test_a_minimal_goal_takes_the_defaults():
    req = parse({"type": "goal", "x": 1, "y": 2})
    assert req == Request("goal", None, (Waypoint(1.0, 2.0),), "odom", False, None)


def test_the_goal_speed_may_equal_the_configured_limit():
    assert parse({"type": "goal", "x": 1, "y": 2, "max_speed": V_MAX}).waypoints[0].max_speed \
        == V_MAX


def test_a_mission_keeps_its_waypoints_in_order():
    req = parse({"id": 7, "type": "mission", "loop": True, "timeout": 30, "waypoints": [
        {"x": 1, "y": 0}, {"x": 1, "y": 1, "tolerance": 0.5}, {"x": 0, "y": 1, "max_speed": 0.1}]})
    assert req.type == "mission" and req.id == 7 and req.loop and req.timeout_s == 30.0
    assert req.waypoints == (Waypoint(1.0, 0.0), Waypoint(1.0, 1.0, 0.5),
                             Waypoint(0.0, 1.0, None, 0.1))


def test_a_mission_may_have_the_maximum_number_of_waypoints():
    req = parse({"type": "mission", "waypoints": [{"x": i, "y": 0} for i in range(MAX_WAYPOINTS)]})
    assert len(req.waypoints) == MAX_WAYPOINTS


def test_subscribe_with_and_without_a_rate():
    assert parse({"type": "subscribe", "id": "s", "rate_hz": 5}).rate_hz == 5.0
    assert parse({"type": "subscribe"}).rate_hz == 2.0


@pytest.mark.parametrize("kind", ["cancel", "pause", "resume", "status", "unsubscribe"])
def test_the_commands_without_arguments(kind):
    assert parse({"v": 1, "id": "c", "type": kind}) == Request(kind, "c")


def test_an_id_of_the_maximum_length_and_an_integer_id_are_accepted():
    assert parse({"type": "cancel", "id": "i" * MAX_ID_CHARS}).id == "i" * MAX_ID_CHARS
    assert parse({"type": "cancel", "id": -(2**53)}).id == -(2**53)


def test_utf8_bytes_with_surrounding_whitespace_are_a_request():
    assert parse(b'  {"type": "status", "id": "\xc3\xa9t\xc3\xa9"}\r ').id == "été"


# --- refused --------------------------------------------------------------------------------

GOAL = {"id": "g", "type": "goal", "x": 1.0, "y": 2.0}


def goal(**fields: object) -> dict:
    return {**GOAL, **fields}


def mission(*points: object, **fields: object) -> dict:
    return {"id": "m", "type": "mission", "waypoints": list(points), **fields}


def raw_goal(x: str) -> bytes:
    """A goal whose x is the literal `x` as written on the wire (json.dumps would refuse it)."""
    return b'{"id": "g", "type": "goal", "x": ' + x.encode() + b', "y": 0}'


# (request, what the message must contain, the id the error echoes)
REFUSED = [
    (b'{"type": "goal", ', "malformed JSON", None),
    (b"", "malformed JSON", None),
    (b"\xff\xfe\xfd{}", "malformed JSON", None),  # not UTF-8
    (b'{"type": "status", "id": "\xff"}', "malformed JSON", None),
    (b"[1, 2]", "JSON object, got list", None),
    (b'"goal"', "JSON object, got str", None),
    (b"null", "JSON object, got NoneType", None),
    (b"[" * 60000, "nested deeper", None),  # beyond the interpreter's recursion limit
    ({"id": 4, "type": "status", "x": [[[[[[[[[1]]]]]]]]]}, "nested deeper", 4),
    ({"id": 5, "type": "dance"}, "unknown request type \"dance\"", 5),
    ({"id": 5}, "unknown request type null", 5),
    ({"id": 5, "type": ["goal"]}, "unknown request type", 5),
    (goal(z=3), "unknown field 'z'", "g"),
    ({"id": "c", "type": "cancel", "x": 1}, "unknown field 'x'", "c"),
    ({"id": "s", "type": "subscribe", "rate": 1}, "unknown field 'rate'", "s"),
    ({"id": "g", "type": "goal", "y": 1}, "'x' is required", "g"),
    ({"id": "g", "type": "goal", "x": 1}, "'y' is required", "g"),
    (goal(x=None), "'x' is required", "g"),
    (raw_goal("1e999"), "'x' must be finite", "g"),
    (raw_goal("-1e999"), "'x' must be finite", "g"),
    (raw_goal("NaN"), "'x' must be finite", "g"),
    (raw_goal("Infinity"), "'x' must be finite", "g"),
    (raw_goal("-Infinity"), "'x' must be finite", "g"),
    (raw_goal("1" + "0" * 400), "'x' must be finite", "g"),  # an int beyond the float range
    (raw_goal("1" + "0" * 5000), "malformed JSON", None),  # beyond int parsing's digit limit
    (goal(x=True), "'x' must be a number, got true", "g"),
    (goal(y=False), "'y' must be a number, got false", "g"),
    (goal(x="1.0"), "'x' must be a number", "g"),
    (goal(x=[1]), "'x' must be a number", "g"),
    (goal(x={"v": 1}), "'x' must be a number", "g"),
    (goal(tolerance=0.01), "'tolerance' must be ≥ 0.05", "g"),
    (goal(tolerance=2.5), "'tolerance' must be ≤ 2", "g"),
    (goal(tolerance=-1), "'tolerance'", "g"),
    (goal(max_speed=0.6), "'max_speed' must be ≤ 0.5", "g"),
    (goal(max_speed=0), "'max_speed' must be > 0", "g"),
    (goal(max_speed=-0.1), "'max_speed' must be > 0", "g"),
    (goal(timeout=0.5), "'timeout' must be ≥ 1", "g"),
    (goal(timeout=1e6), "'timeout' must be ≤ 86400", "g"),
    (goal(frame="map"), "'frame' must be one of odom, relative", "g"),
    (goal(frame=None), "'frame'", "g"),
    (goal(v=2), "unsupported protocol version 2", "g"),
    (goal(v=True), "unsupported protocol version true", "g"),
    (goal(v="1"), "unsupported protocol version \"1\"", "g"),
    (goal(v=0), "unsupported protocol version 0", "g"),
    (goal(id="i" * (MAX_ID_CHARS + 1)), "'id' longer than 128", None),
    (goal(id=1.5), "'id' must be a string or an integer", None),
    (goal(id=True), "'id' must be a string or an integer", None),
    (goal(id=[1]), "'id' must be a string or an integer", None),
    (goal(id=2**53 + 1), "'id' integer out of range", None),
    (mission(*[{"x": 0, "y": 0}] * (MAX_WAYPOINTS + 1)), "'waypoints' must be a list of 1 to 100",
     "m"),
    (mission(), "'waypoints' must be a list of 1 to 100", "m"),
    ({"id": "m", "type": "mission"}, "'waypoints' must be a list", "m"),
    ({"id": "m", "type": "mission", "waypoints": {"x": 1, "y": 1}}, "'waypoints'", "m"),
    (mission({"x": 0, "y": 0}, 3), "waypoint 2: must be an object", "m"),
    (mission({"x": 0, "y": 0}, {"x": 1}), "waypoint 2: 'y' is required", "m"),
    (mission({"x": 0, "y": 0, "z": 1}), "waypoint 1: unknown field 'z'", "m"),
    (mission({"x": 0, "y": 0, "tolerance": 9}), "waypoint 1: 'tolerance' must be ≤ 2", "m"),
    (mission({"x": 0, "y": 0, "max_speed": 1}), "waypoint 1: 'max_speed' must be ≤ 0.5", "m"),
    (mission({"x": 0, "y": 0}, loop="yes"), "'loop' must be true or false", "m"),
    (mission({"x": 0, "y": 0}, loop=1), "'loop' must be true or false", "m"),
    (mission({"x": 0, "y": 0}, x=1), "unknown field 'x'", "m"),
    ({"id": "s", "type": "subscribe", "rate_hz": 0}, "'rate_hz' must be > 0", "s"),
    ({"id": "s", "type": "subscribe", "rate_hz": 21}, "'rate_hz' must be ≤ 20", "s"),
]


@pytest.mark.parametrize(("request_", "message", "rid"), REFUSED,
                         ids=[str(i) for i in range(len(REFUSED))])
def test_malformed_requests_are_refused_naming_the_field(request_, message, rid):
    error = refused(request_)
    assert message in str(error)
    assert error.request_id == rid


def test_an_error_message_quotes_a_long_bad_value_briefly():
    error = refused(goal(x="a" * 10000))
    assert len(str(error)) < 100


# --- properties -----------------------------------------------------------------------------

FUZZ = settings(max_examples=300, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow])

json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=10),
    lambda children: st.lists(children, max_size=4)
    | st.dictionaries(st.sampled_from(["v", "id", "type", "x", "y", "tolerance", "max_speed",
                                       "frame", "loop", "timeout", "waypoints", "rate_hz", "z"]),
                      children, max_size=6),
    max_leaves=20)
request_like = st.fixed_dictionaries(
    {}, optional={"v": json_values | st.just(1), "id": json_values,
                  "type": st.sampled_from(["goal", "mission", "cancel", "subscribe", "status",
                                           "nope"]) | json_values,
                  "x": json_values, "y": json_values, "tolerance": json_values,
                  "max_speed": json_values, "frame": st.sampled_from(["odom", "relative"]),
                  "timeout": json_values, "loop": json_values, "rate_hz": json_values,
                  "waypoints": st.lists(st.fixed_dictionaries(
                      {"x": json_values, "y": json_values}), max_size=3) | json_values})


def _finite_numbers(req: Request) -> bool:
    numbers = [req.rate_hz, req.timeout_s or 0.0]
    for w in req.waypoints:
        numbers += [w.x, w.y, w.tolerance or 0.1, w.max_speed or 0.1]
    return all(isinstance(n, float) and math.isfinite(n) for n in numbers)


@FUZZ
@given(st.binary(max_size=300))
def test_any_bytes_give_a_request_or_a_protocol_error(line):
    try:
        req = parse_request(line, V_MAX)
    except ProtocolError:
        return
    assert _finite_numbers(req)


@FUZZ
@given(request_like)
def test_any_json_gives_a_request_or_a_protocol_error_and_accepted_numbers_are_in_range(obj):
    try:
        req = parse_request(json.dumps(obj).encode(), V_MAX)
    except ProtocolError as exc:
        assert exc.request_id is None or exc.request_id == obj.get("id")
        return
    assert _finite_numbers(req)
    for w in req.waypoints:
        assert w.tolerance is None or 0.05 <= w.tolerance <= 2.0
        assert w.max_speed is None or 0.0 < w.max_speed <= V_MAX
    assert req.timeout_s is None or 1.0 <= req.timeout_s <= 86400.0
    assert 0.0 < req.rate_hz <= 20.0


@FUZZ
@given(st.integers(min_value=1, max_value=3 * MAX_DEPTH))
def test_nesting_deeper_than_the_limit_is_refused(depth):
    line = b'{"id": 1, "type": "status", "z": ' + b"[" * depth + b"]" * depth + b"}"
    if depth + 1 <= MAX_DEPTH:
        with pytest.raises(ProtocolError, match="unknown field 'z'"):
            parse_request(line, V_MAX)
    else:
        with pytest.raises(ProtocolError, match="nested deeper") as info:
            parse_request(line, V_MAX)
        assert info.value.request_id == 1


# --- encode and reply -----------------------------------------------------------------------

def _strict(line: bytes) -> object:
    def no_constants(name: str) -> object:
        raise AssertionError(f"{name} is not JSON")
    return json.loads(line, parse_constant=no_constants)


def test_encode_writes_non_finite_floats_as_null():
    line = encode({"a": math.nan, "b": [math.inf, -math.inf, 1.5], "c": {"d": (math.nan, 2)}})
    assert line.endswith(b"\n") and line.count(b"\n") == 1
    assert b"NaN" not in line and b"Infinity" not in line
    assert _strict(line) == {"a": None, "b": [None, None, 1.5], "c": {"d": [None, 2]}}


@FUZZ
@given(st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(),
                    lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(), c, max_size=4),
                    max_leaves=30))
def test_encode_never_emits_nan_or_a_second_line(value):
    line = encode({"value": value})
    assert line.endswith(b"\n") and line.count(b"\n") == 1
    decoded = _strict(line)
    assert isinstance(decoded, dict) and set(decoded) == {"value"}


def test_reply_ok_and_error():
    assert reply("a", state="idle") == {"v": 1, "type": "reply", "id": "a", "ok": True,
                                        "state": "idle"}
    assert reply(None, False, "nope") == {"v": 1, "type": "reply", "id": None, "ok": False,
                                          "error": "nope"}
