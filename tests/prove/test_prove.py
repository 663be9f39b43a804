"""The proof's scoring and bookkeeping (the diagnosis itself: test_diagnose.py)."""

import json

from hartrao_jax.prove._prove import CASES, Score, _write, merge_results, score


def _case(name):
    return next(c for c in CASES if c.name == name)


def _doc(findings=(), confounded=()):
    return {"findings": list(findings), "confounded": list(confounded)}


def test_instrument_finding_is_scored_against_the_truth():
    truth = {"effects": {"x2": 1e-4}, "scans": [{"id": "a"}, {"id": "b"}]}
    f = {"effect": "x2", "scans": ["a", "b"], "estimate": {"x2": {"value": 1.1e-4,
                                                                  "sigma": 1e-5}},
         "sigma0_before": 1.01, "sigma0_after": 1.0, "rms_before_m": 8e-4, "rms_after_m": 7e-4}
    s = score(_case("x2"), _doc([f]), truth, 1, 1.0)
    assert (s.found, s.located, s.estimate_ok, s.improved, s.false) == (True, True, True, True, [])
    f["estimate"]["x2"]["value"] = 1.4e-4  # 4 sigma off
    assert score(_case("x2"), _doc([f]), truth, 1, 1.0).estimate_ok is False


def test_confounded_parameters_must_not_be_findings():
    truth = {"effects": {"x10": 1e-3}, "scans": [{"id": "a"}]}
    conf = {"effect": "x10", "with": ["tz", "f"], "correlation": 0.99999}
    assert score(_case("x10"), _doc(confounded=[conf]), truth, 1, 1.0).found
    bad = _doc([{"effect": "x10", "scans": ["a"], "estimate": {}}], [conf])
    s = score(_case("x10"), bad, truth, 1, 1.0)
    assert not s.found and s.false == ["x10"]


def test_clean_case_counts_every_finding_but_panels_as_false():
    s = score(_case("clean"), _doc([{"effect": "panel_offset"}, {"effect": "x5n"}]), {}, 1, 1.0)
    assert not s.found and s.false == ["x5n"]


def test_merge_gives_one_table_of_the_parts(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    for d, case, n in ((a, "x2", 3), (b, "oscillation", 2)):
        d.mkdir()
        sc = [Score(case, k + 1, True, True, k > 0, True, [], 2.0) for k in range(n)]
        _write(d, [_case(case)], sc, {case: []}, n, 0.01, 5.0)
    res = merge_results(tmp_path / "m", [a, b])
    rows = {r["case"]: r for r in res["table"]}
    assert rows["x2"]["found"] == "3/3" and rows["x2"]["estimate"] == "2/3"
    assert rows["oscillation"]["seeds"] == 2
    doc = json.loads((tmp_path / "m" / "prove.json").read_text())
    assert len(doc["runs"]) == 5 and doc["elapsed_s"] == 10.0


def test_a_compact_bump_is_found_as_the_catalog_local_deformation():
    """The concealed Gaussian bump is the catalog's shape: a local_deformation finding at its
    place is the bump found (and scored against its amplitude and width)."""
    import math

    truth = {"reflector": {"bump": [3e-3, 5.0, math.radians(30.0), 0.3]}, "scans": [],
             "effects": {}}
    x0, y0 = 5.0 * math.cos(math.radians(30.0)), 5.0 * math.sin(math.radians(30.0))
    f = {"effect": "local_deformation", "scans": ["a"], "where": {"x_m": x0 + 0.05, "y_m": y0},
         "estimate": {"amplitude_m": {"value": 2.9e-3, "sigma": 1e-4},
                      "width_m": {"value": 0.31, "sigma": 0.02}},
         "sigma0_before": 1.01, "sigma0_after": 1.0, "rms_before_m": 8e-4, "rms_after_m": 7e-4}
    s = score(_case("unexplained_bump"), _doc([f]), truth, 1, 1.0)
    assert (s.found, s.located, s.estimate_ok, s.false) == (True, True, True, [])
    f["where"]["x_m"] += 2.0
    assert score(_case("unexplained_bump"), _doc([f]), truth, 1, 1.0).located is False


def test_a_held_width_scores_the_amplitude_alone():
    truth = {"reflector": {"local": [1e-3, 4.0, 3.0, 0.6]}, "scans": [], "effects": {}}
    f = {"effect": "local_deformation", "scans": ["a"], "where": {"x_m": 4.0, "y_m": 3.0},
         "estimate": {"amplitude_m": {"value": 0.95e-3, "sigma": 1e-4},
                      "width_m": {"value": 0.5, "sigma": None}},
         "sigma0_before": 1.01, "sigma0_after": 1.0, "rms_before_m": 8e-4, "rms_after_m": 7e-4}
    assert score(_case("local_deformation"), _doc([f]), truth, 1, 1.0).estimate_ok is True


def test_expected_effect_named_as_the_alternative_is_counted_apart():
    """x1n accepted where x5n was simulated, x5n named as the alternative the data hardly tell
    apart (the diagnosis' ``alternatives``): still a false finding, counted as ambiguous."""
    f = {"effect": "x1n", "scans": ["a"], "estimate": {},
         "alternatives": [{"effect": "x5n", "correlation": -0.986, "likelihood_ratio": 1.9}]}
    s = score(_case("x5n"), _doc([f]), {"effects": {"x5n": 3e-5}, "scans": [{"id": "a"}]}, 1, 1.0)
    assert (s.found, s.false, s.as_alternative) == (False, ["x1n"], True)
    s = score(_case("x5n"), _doc([{**f, "alternatives": []}]), {}, 1, 1.0)
    assert s.as_alternative is False


def test_mahalanobis_limit_is_the_chi2_quantile():
    """The joint check of several estimates against the truth takes the 99.73 % chi-square
    quantile from scipy.special (scipy.stats is not imported by the diagnose command)."""
    import numpy as np
    from scipy import stats

    from hartrao_jax.prove._prove import _mahalanobis_ok

    for q in (1, 2, 3, 7, 20):
        cov = np.diag(np.full(q, 4.0))
        limit = stats.chi2.ppf(0.9973, q)
        d = np.full(q, 2.0 * np.sqrt(limit / q))  # d2 = limit exactly, up to rounding
        ok, d2 = _mahalanobis_ok(d * (1 - 1e-9), np.zeros(q), cov)
        assert ok and abs(d2 - limit) < 1e-6 * limit
        assert not _mahalanobis_ok(d * (1 + 1e-9), np.zeros(q), cov)[0]
