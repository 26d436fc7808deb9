"""The settings a policy was trained with against those it runs with: what is recorded, what
counts as a difference, what an older record is compared from, and the lines the operator sees."""

from __future__ import annotations

import json
import logging

from runtime.config.settings import load_config
from runtime.jobs.trained_settings import (
    RECORD_KEY,
    decision_settings,
    trained_settings_report,
)


def _config(*overrides: str):
    return load_config(None, list(overrides)).config


def test_the_record_holds_what_shapes_decisions_and_not_the_machine():
    record = decision_settings(_config())
    sections = {key.split(".")[0] for key in record}
    assert sections == {"robot", "loop", "odometry", "perception", "memory", "tracking", "dwa",
                        "shield", "recovery", "limits"}
    assert [k for k in record if k.startswith("loop.")] == ["loop.control_hz"]
    # derived copies (dwa.robot_radius_m from robot.radius_m) are not keys of their own
    assert "robot.radius_m" in record and "dwa.robot_radius_m" not in record
    assert json.loads(json.dumps(record)) == record  # plain JSON, tuples as lists


def test_a_record_equal_to_the_running_config_reports_nothing(caplog):
    training = {RECORD_KEY: json.loads(json.dumps(decision_settings(_config())))}
    report = trained_settings_report(training, _config())
    assert report.basis == "its training record"
    assert report.differences == () and report.unmatched == ()
    with caplog.at_level(logging.INFO, logger="safemove.policy"):
        report.log("actor.onnx")
    assert caplog.records == []


def test_each_differing_key_is_one_warning_naming_both_values(caplog):
    training = {RECORD_KEY: decision_settings(_config("dwa.weight_evasion=3.0",
                                                      "robot.radius_m=0.2"))}
    report = trained_settings_report(training, _config("dwa.weight_evasion=0.0"))
    assert [d.as_dict() for d in report.differences] == [
        {"key": "robot.radius_m", "trained": 0.2, "running": 0.17},
        {"key": "dwa.weight_evasion", "trained": 3.0, "running": 0.0}]
    with caplog.at_level(logging.INFO, logger="safemove.policy"):
        report.log("actor.onnx")
    lines = [r.getMessage() for r in caplog.records]
    assert [r.levelname for r in caplog.records] == ["WARNING", "WARNING"]
    assert lines[1] == ("actor.onnx: trained with dwa.weight_evasion=3.0, running with 0.0"
                        " (its training record)")


def test_an_integer_and_the_same_float_are_the_same_value():
    record = decision_settings(_config("dwa.weight_evasion=2.0"))
    record["dwa.weight_evasion"] = 2  # JSON writes 2.0 as 2 in some writers
    running = _config("dwa.weight_evasion=2.0")
    assert trained_settings_report({RECORD_KEY: record}, running).differences == ()


def test_keys_only_one_side_has_are_listed_not_compared(caplog):
    record = decision_settings(_config())
    record["dwa.retired_weight"] = 1.0
    del record["robot.radius_m"]
    report = trained_settings_report({RECORD_KEY: record}, _config())
    assert report.differences == ()
    assert "dwa.retired_weight" in report.unmatched and len(report.unmatched) == 2
    with caplog.at_level(logging.INFO, logger="safemove.policy"):
        report.log("actor.onnx")
    (line,) = caplog.records
    assert line.levelname == "INFO" and "2 setting(s) not in both" in line.getMessage()


def test_an_older_record_is_compared_as_todays_defaults_with_its_overrides():
    training = {"settings": {"config": None, "overrides": ["dwa.weight_evasion=1.5"]}}
    report = trained_settings_report(training, _config())
    assert "today's defaults with dwa.weight_evasion=1.5" in str(report.basis)
    assert [d.key for d in report.differences] == ["dwa.weight_evasion"]
    same = trained_settings_report(training, _config("dwa.weight_evasion=1.5"))
    assert same.differences == ()


def test_without_a_usable_record_nothing_is_compared_and_one_line_says_so(caplog):
    cases = [None, {}, {"settings": {"config": "/elsewhere/robot.yaml", "overrides": []}},
             {"settings": {"config": None, "overrides": ["dwa.no_such_key=1"]}},
             {"settings": {"config": None, "overrides": "dwa.weight_evasion=3.0"}}]
    for training in cases:
        report = trained_settings_report(training, _config())
        assert report.basis is None and report.differences == (), training
    with caplog.at_level(logging.INFO, logger="safemove.policy"):
        report.log("actor.onnx")
    (line,) = caplog.records
    assert "no record of the settings it was trained with" in line.getMessage()
