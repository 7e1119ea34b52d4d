"""`benchmarks.fit_global`'s calibration of the reported standard errors: over all runs and over
the runs the library does not flag (the ones whose standard errors it vouches for)."""

import math

from benchmarks.fit_global import _summary, markdown


def _run(flagged, z, flags=(), z_determined=None):
    return {"success": True, "flagged": flagged, "z": z, "fit_s": 1.0, "compile_s": 0.0,
            "position_err_of_scene": 0.0, "flags": list(flags), "z_determined": z if z_determined is None else z_determined}


def test_calibration_over_unflagged_runs():
    runs = [_run(True, [0.5, 9.0, 15.0], ["undetermined"], [0.5, 9.0]), _run(False, [0.1, -1.9, 2.5, 0.3]),
            _run(False, [-0.2]), _run(True, [30.0], ["wrong_minimum"])]
    s = _summary(runs)
    assert s["calibration_n"] == 9 and math.isclose(s["calibration_within_2se"], 5 / 9)
    assert s["calibration_unflagged_n"] == 5 and s["unflagged_runs"] == 2
    assert math.isclose(s["calibration_unflagged_within_2se"], 4 / 5)
    # determined parameters of the runs flagged for nothing but "undetermined": 7 of which 5 within 2
    assert s["calibration_determined_n"] == 7 and math.isclose(s["calibration_determined_within_2se"], 5 / 7)
    assert "80 % of 5 (2 runs) | 71 % of 7 |" in markdown({"settings": {"noisy": {**s, "runs": runs}}})
    none = _summary([_run(True, [1.0])])
    assert none["calibration_unflagged_n"] == 0 and math.isnan(none["calibration_unflagged_within_2se"])
    assert "none unflagged" in markdown({"settings": {"noisy": {**none, "runs": []}}})


def test_calibration_of_covered_quantities():
    """The covered quantities' fractions: within 2 standard errors over all runs, over those
    marked determined, and inside the projected joint interval (`zq_joint`: errors over half
    the interval); each counted over every run, flagged or not."""
    runs = [{**_run(True, [0.5], ["undetermined"]), "zq": [0.5, 2.5, -3.0], "zq_determined": [0.5],
             "zq_joint": [0.2, 0.9, -1.1]},
            {**_run(False, [0.1]), "zq": [1.0, -2.2], "zq_determined": [1.0, -2.2], "zq_joint": [0.4, -2.1]}]
    s = _summary(runs)
    assert s["calibration_zq_n"] == 5 and math.isclose(s["calibration_zq_within_2se"], 2 / 5)
    assert s["calibration_zq_determined_n"] == 3 and math.isclose(s["calibration_zq_determined_within_2se"], 2 / 3)
    assert s["calibration_zq_joint_n"] == 5 and math.isclose(s["calibration_zq_joint_within_2se"], 4 / 5)
    assert "| 40 % of 5 / 67 % of 3 / 80 % |" in markdown({"settings": {"noisy": {**s, "runs": runs}}})
