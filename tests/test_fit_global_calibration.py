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
