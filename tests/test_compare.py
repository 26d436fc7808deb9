"""safemove compare: Wilson intervals, McNemar's exact test on seed-paired episodes, Welch's
t-test between training runs, the outcomes counted, and the refusals of results that are not
the same episodes."""

import json
import math
from pathlib import Path

import pytest
from scipy.stats import t as student_t

from runtime.errors import UserError
from sim_stub.binomial import mcnemar_exact_p, wilson_interval
from sim_stub.compare import Outcome, compare, load_evaluation, table


def _wilson(k: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """The Wilson score interval from its formula, the oracle for scipy's."""
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return centre - half, centre + half


def _result(path, outcomes: dict[str, list[str]], first_seed: int = 0, **conditions) -> Path:
    """A `safemove eval --json`-shaped result: per scenario, statuses for consecutive seeds."""
    episodes = [{"scenario": name, "seed": first_seed + i, "status": status}
                for name, statuses in outcomes.items() for i, status in enumerate(statuses)]
    result = {"fps": 15.0, "noise": True, "crowd": "scenario", "camera_hfov_deg": 87.0,
              **conditions, "episodes": episodes}
    path.write_text(json.dumps(result))
    return path


@pytest.mark.parametrize("k, n", [(0, 10), (10, 10), (73, 100), (135, 200), (1, 3)])
def test_wilson_interval_matches_its_formula_and_stays_in_the_unit_interval(k, n):
    lo, hi = wilson_interval(k, n)
    assert (lo, hi) == pytest.approx(_wilson(k, n), abs=1e-9)
    assert 0.0 <= lo <= k / n <= hi <= 1.0


def test_mcnemar_exact_counts_only_the_discordant_pairs():
    assert mcnemar_exact_p(0, 6) == pytest.approx(2 * 0.5 ** 6)  # all six one way
    assert mcnemar_exact_p(6, 0) == mcnemar_exact_p(0, 6)  # two-sided
    assert mcnemar_exact_p(3, 3) == pytest.approx(1.0)
    assert mcnemar_exact_p(0, 0) == 1.0  # no discordant episode: no evidence either way
    # P(X <= 2) for X ~ Bin(10, 1/2), doubled
    assert mcnemar_exact_p(2, 8) == pytest.approx(2 * (1 + 10 + 45) / 1024)


def test_compare_pairs_episodes_by_seed_and_pools_files_under_one_label(tmp_path):
    dwa = [_result(tmp_path / "dwa.json", {"a": ["success", "collision", "success", "timeout"]}),
           _result(tmp_path / "d1.json", {"a": ["success", "collision"]}, first_seed=1000)]
    policy = [_result(tmp_path / "p0.json", {"a": ["collision", "success", "success", "success"]}),
              _result(tmp_path / "p1.json", {"a": ["success", "success"]}, first_seed=1000)]
    out = compare([load_evaluation("dwa", [dwa]), load_evaluation("policy", [policy])])
    a = out["scenarios"]["a"]
    assert a["rates"]["dwa"]["rate"] == 0.5 and a["rates"]["dwa"]["episodes"] == 6
    assert a["rates"]["policy"]["rate"] == pytest.approx(5 / 6)
    assert a["rates"]["policy"]["ci95"] == pytest.approx(list(_wilson(5, 6)))
    # seed 0 only the reference; seeds 1, 3 and 1001 only the policy
    paired = a["against_reference"]["policy"]
    assert (paired["only_reference"], paired["only_this"]) == (1, 3)
    assert paired["difference"] == pytest.approx(2 / 6)
    assert paired["p_value"] == pytest.approx(mcnemar_exact_p(1, 3))
    assert out["reference"] == "dwa" and out["sources"]["policy"][0][1].endswith("p1.json")


def test_compare_refuses_results_that_are_not_the_same_episodes(tmp_path):
    ref = load_evaluation("dwa", [[_result(tmp_path / "r.json", {"a": ["success"] * 4})]])
    short = load_evaluation("p", [[_result(tmp_path / "s.json", {"a": ["success"] * 3})]])
    with pytest.raises(UserError, match=r"p has 3 seeds \(0-2\) of a, dwa 4 seeds \(0-3\)"):
        compare([ref, short])
    reactive = load_evaluation("q", [[_result(tmp_path / "c.json", {"a": ["success"] * 4},
                                              crowd="reactive")]])
    other_room = load_evaluation("r2", [[_result(tmp_path / "b.json", {"a": ["success"] * 4,
                                                                      "b": ["success"]})]])
    with pytest.raises(UserError, match=r"r2 has scenarios \['a', 'b'\], dwa \['a'\]"):
        compare([ref, other_room])  # b would be dropped unseen
    with pytest.raises(UserError, match="crowd=reactive"):
        compare([ref, reactive])
    # results from before --camera-hfov existed ran at the D435's 87 deg
    old = load_evaluation("old", [[_result(tmp_path / "o.json", {"a": ["success"] * 4},
                                           camera_hfov_deg=None)]])
    assert compare([ref, old])["scenarios"]["a"]["against_reference"]["old"]["p_value"] == 1.0
    # the refusal names what makes other episodes, not a sensing what-if beside it
    clean = load_evaluation("clean", [[_result(tmp_path / "n.json", {"a": ["success"] * 4},
                                               noise=False, surround_people=True)]])
    with pytest.raises(UserError, match=r"clean ran with noise=False \(against True\) in dwa:"):
        compare([ref, clean])
    with pytest.raises(UserError, match="seed 0 appears twice"):
        load_evaluation("twice", [[tmp_path / "r.json", tmp_path / "r.json"]])
    # a second run of one planner may repeat the first's seeds, but must have them all
    runs = load_evaluation("runs", [[tmp_path / "r.json"], [tmp_path / "s.json"]])
    with pytest.raises(UserError, match=r"runs run 2 has 3 seeds \(0-2\) of a"):
        compare([load_evaluation("dwa", [[tmp_path / "r.json"], [tmp_path / "r.json"]]), runs])
    with pytest.raises(UserError, match="dwa has 1 run\\(s\\), both 2: give one run each"):
        compare([ref, load_evaluation("both", [[tmp_path / "r.json"], [tmp_path / "r.json"]])])


def test_several_runs_each_compare_between_runs_by_welch(tmp_path):
    def runs(name, successes_per_run):  # one file per run, ten seeds of scenario a
        return [[_result(tmp_path / f"{name}{i}.json",
                         {"a": ["success"] * k + ["collision"] * (10 - k)})]
                for i, k in enumerate(successes_per_run)]

    ref = load_evaluation("ref", runs("r", [5, 6, 7]))
    new = load_evaluation("new", runs("n", [8, 9]))
    out = compare([ref, new])["scenarios"]["a"]
    assert out["rates"]["ref"]["run_rates"] == pytest.approx([0.5, 0.6, 0.7])
    # Student's t interval of the mean of three runs: 0.6 +- t(0.975, 2) * 0.1 / sqrt(3)
    half = student_t.ppf(0.975, 2) * 0.1 / math.sqrt(3)
    assert out["rates"]["ref"]["ci95"] == pytest.approx([0.6 - half, 0.6 + half])
    # Welch's test from its formula: variances 0.01 and 0.005, Welch-Satterthwaite's df
    va, vb = 0.01 / 3, 0.005 / 2
    t = 0.25 / math.sqrt(va + vb)
    df = (va + vb) ** 2 / (va ** 2 / 2 + vb ** 2 / 1)
    c = out["against_reference"]["new"]
    assert c["difference"] == pytest.approx(0.25)
    assert c["p_value"] == pytest.approx(2 * student_t.sf(t, df))
    half = student_t.ppf(0.975, df) * math.sqrt(va + vb)
    assert c["ci95"] == pytest.approx([0.25 - half, 0.25 + half])
    # runs without any spread: the interval is the rate, equal means are no difference
    same = compare([load_evaluation("x", runs("x", [4, 4])),
                    load_evaluation("y", runs("y", [4, 4]))])
    assert same["scenarios"]["a"]["rates"]["x"]["ci95"] == [0.4, 0.4]
    assert same["scenarios"]["a"]["against_reference"]["y"]["p_value"] == 1.0


def test_collisions_split_by_how_long_the_person_had_been_in_view(tmp_path):
    # seconds in view at contact: None a fixed obstacle, 0 out of view, then 0.5 s and 1 s
    episodes = [{"scenario": "a", "seed": i, "status": status, "contact_in_view_s": seen}
                for i, (status, seen) in enumerate([
                    ("success", None), ("timeout", None), ("collision", None),
                    ("collision", 0.0), ("collision", 0.5), ("collision", 1.0),
                    ("collision", 2.5)])]
    path = tmp_path / "r.json"
    path.write_text(json.dumps({"episodes": episodes}))

    def counted(*outcome):
        run = load_evaluation("p", [[path]], Outcome(*outcome)).runs[0]
        return sorted(seed for seed, has in run.outcome["a"].items() if has)

    assert counted("success") == [0]
    assert counted("collision") == [2, 3, 4, 5, 6]
    assert counted("seen-collision") == [5, 6]
    assert counted("unseen-collision") == [2, 3, 4]
    assert counted("seen-collision", 0.5) == [4, 5, 6]  # a shorter look counts as seen
    assert counted("unseen-collision", 2.0) == [2, 3, 4, 5]
    out = compare([load_evaluation("p", [[path]], Outcome("seen-collision"))])
    assert out["outcome"] == "seen-collision (1 s)"
    assert out["scenarios"]["a"]["rates"]["p"]["rate"] == pytest.approx(2 / 7)
    # a result from before contact_in_view_s was recorded cannot tell seen from unseen
    old = _result(tmp_path / "old.json", {"a": ["success", "collision"]})
    assert load_evaluation("old", [[old]], Outcome("collision")).runs[0].outcome["a"] == {
        0: False, 1: True}
    with pytest.raises(UserError, match=r"episodes\[1\] \(a seed 1\) has no number in"
                                        r" 'contact_in_view_s', which --outcome seen-collision"):
        load_evaluation("old", [[old]], Outcome("seen-collision"))
    bad = tmp_path / "bad.json"
    for lie in ("2 s", True, 10**400, float("nan"), float("inf")):
        bad.write_text(json.dumps({"episodes": [{"scenario": "a", "seed": 0, "status": "collision",
                                                 "contact_in_view_s": lie}]}))
        with pytest.raises(UserError, match=r"episodes\[0\] \(a seed 0\) has no number in"):
            load_evaluation("bad", [[bad]], Outcome("unseen-collision"))
    with pytest.raises(ValueError, match="outcome 'collisions'"):
        Outcome("collisions")


@pytest.mark.parametrize("content, message", [
    (None, "No such file"),
    ("{not json", "not a `safemove eval --json` result"),
    ('{"scenarios": {}}', "no 'episodes' list"),
    ('{"episodes": []}', "no episodes"),
    ('{"episodes": [3]}', r"episodes\[0\] lacks"),
    ('{"episodes": [{"scenario": "a", "seed": 0}]}', r"episodes\[0\] lacks"),
    ('{"episodes": [{"scenario": "a", "seed": "0", "status": "success"}]}', "bad scenario or seed"),
])
def test_a_bad_result_file_is_one_line_naming_it(tmp_path, content, message):
    path = tmp_path / "bad.json"
    if content is not None:
        path.write_text(content)
    with pytest.raises(UserError, match=message) as err:
        load_evaluation("bad", [[path]])
    assert str(path) in str(err.value)


def test_compare_cli_prints_the_table_and_json_and_refuses_with_exit_2(tmp_path, safemove):
    ref = _result(tmp_path / "dwa.json", {"a": ["success", "collision"] * 5})
    val = _result(tmp_path / "dwa_val.json", {"a": ["success"] * 2}, first_seed=1000)
    new = _result(tmp_path / "new.json", {"a": ["success"] * 10})
    new_val = _result(tmp_path / "new_val.json", {"a": ["collision"] * 2}, first_seed=1000)
    run = safemove(["compare", f"dwa={ref}+{val}", f"new={new}+{new_val}"])
    assert run.wait(timeout=60) == 0, run.stderr[-2000:]
    result = json.loads(run.stdout)
    paired = result["scenarios"]["a"]["against_reference"]["new"]
    assert (paired["only_reference"], paired["only_this"]) == (2, 5)
    assert "95 % CI" in run.stderr and "+25.0 pts" in run.stderr
    runs = safemove(["compare", f"dwa={ref},{ref}", f"new={new},{ref}", "--json"])
    assert runs.wait(timeout=60) == 0, runs.stderr[-2000:]
    between = json.loads(runs.stdout)["scenarios"]["a"]["against_reference"]["new"]
    assert between["test"] == "welch t over runs" and between["difference"] == pytest.approx(0.25)
    collisions = safemove(["compare", f"dwa={ref}", f"new={new}", "--outcome", "collision"])
    assert collisions.wait(timeout=60) == 0, collisions.stderr[-2000:]
    fewer = json.loads(collisions.stdout)["scenarios"]["a"]["against_reference"]["new"]
    assert fewer["difference"] == pytest.approx(-0.5) and "outcome: collision" in collisions.stderr
    bad = safemove(["compare", f"dwa={ref}", f"new={new}", "--seen-s", "nan"])
    assert bad.wait(timeout=60) == 2
    (line,) = bad.stderr.strip().splitlines()
    assert "--seen-s nan" in line and "Traceback" not in line
    same = safemove(["compare", str(ref), str(ref)])
    assert same.wait(timeout=60) == 2
    assert "a label appears twice" in same.stderr and "Traceback" not in same.stderr
    missing = safemove(["compare", f"dwa={ref}", f"new={tmp_path / 'none.json'}"])
    assert missing.wait(timeout=60) == 2
    (line,) = missing.stderr.strip().splitlines()
    assert "none.json" in line and "Traceback" not in line


def test_sensing_what_ifs_pair_with_the_camera_alone_but_never_pool_with_it(tmp_path):
    """A wider camera or people seen all around: the same episodes, the robot knowing more, so
    what it buys is paired by episode; one planner's pooled files must agree on it."""
    camera = _result(tmp_path / "c.json", {"a": ["collision", "collision", "success", "success"]})
    around = _result(tmp_path / "s.json", {"a": ["success"] * 4}, surround_people=True)
    wide = _result(tmp_path / "w.json", {"a": ["success"] * 3 + ["collision"]},
                   camera_hfov_deg=120.0)
    out = compare([load_evaluation("camera", [[camera]]), load_evaluation("around", [[around]]),
                   load_evaluation("wide", [[wide]])])
    paired = out["scenarios"]["a"]["against_reference"]
    assert (paired["around"]["only_reference"], paired["around"]["only_this"]) == (0, 2)
    assert (paired["wide"]["only_reference"], paired["wide"]["only_this"]) == (1, 2)
    assert out["sensing"]["around"] == {"camera_hfov_deg": 87.0, "surround_people": True}
    assert out["sensing"]["wide"] == {"camera_hfov_deg": 120.0, "surround_people": False}
    text = table(out)
    assert "around sees every person around (--surround-people)" in text
    assert "wide sees a 120 deg camera" in text and "camera sees" not in text
    # results from before --surround-people existed saw people with the camera alone
    old = _result(tmp_path / "o.json", {"a": ["success"] * 4}, first_seed=4)
    assert load_evaluation("old", [[old]]).conditions["surround_people"] is False
    with pytest.raises(UserError, match=r"s\.json: ran with surround_people=True \(against"
                                        r" False\)"):
        load_evaluation("mixed", [[old, around]])
