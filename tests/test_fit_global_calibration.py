"""`benchmarks.fit_global`'s calibration of the reported standard errors: over all runs and over
the runs the library does not flag (the ones whose standard errors it vouches for)."""

import math

from benchmarks.fit_global import _summary, markdown


def _run(flagged, z):
    return {"success": True, "flagged": flagged, "z": z, "fit_s": 1.0, "compile_s": 0.0,
            "position_err_of_scene": 0.0}


def test_calibration_over_unflagged_runs():
    runs = [_run(True, [0.5, 9.0, 15.0]), _run(False, [0.1, -1.9, 2.5, 0.3]), _run(False, [-0.2])]
    s = _summary(runs)
    assert s["calibration_n"] == 8 and math.isclose(s["calibration_within_2se"], 5 / 8)
    assert s["calibration_unflagged_n"] == 5 and s["unflagged_runs"] == 2
    assert math.isclose(s["calibration_unflagged_within_2se"], 4 / 5)
    assert "80 % of 5 (2 runs)" in markdown({"settings": {"noisy": {**s, "runs": runs}}})
    none = _summary([_run(True, [1.0])])
    assert none["calibration_unflagged_n"] == 0 and math.isnan(none["calibration_unflagged_within_2se"])
    assert "none unflagged" in markdown({"settings": {"noisy": {**none, "runs": []}}})
