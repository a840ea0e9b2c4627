"""The surge-front metric used by the accuracy-vs-time study, on synthetic simulate outputs."""
import json
import math

import numpy as np
import pytest

from stages.simulate.validation import read_reference, surge_front_error

from conftest import TESTS

REF = TESTS / "data" / "martin_moyce_1952.csv"


def _fake_output(tmp_path, fronts, fps, spacing=0.01, mpu=1.0):
    d = tmp_path / "particles"
    d.mkdir(parents=True, exist_ok=True)
    ext = [[f, 0.0, 0.0] for f in fronts]
    (d / "meta.json").write_text(json.dumps({"fps": fps, "spacing": spacing, "meters_per_unit": mpu,
                                             "stats": {"extent_max": ext}}))
    return tmp_path


@pytest.mark.parametrize("scale", [1.0, 1.1])
def test_surge_front_error_measures_the_distance_to_the_experiment(tmp_path, scale):
    a, g, fps, l0 = 0.25, 9.81, 240, 0.01
    ref = read_reference(REF, "a_2.25in")
    t = np.arange(0, 120) / fps
    T = t * math.sqrt(2 * g / a)
    front = scale * np.interp(T, np.r_[0.0, ref[:, 0]], np.r_[1.0, ref[:, 1]]) * a - 0.5 * l0  # particle centres
    err = surge_front_error(_fake_output(tmp_path, front, fps, l0), study_dir=TESTS, reference="data/martin_moyce_1952.csv",
                            series="a_2.25in", column_width=a, back_wall=0.0)
    assert err == pytest.approx(scale - 1.0, abs=2e-3)


def test_surge_front_error_in_centimetres_uses_metres_for_T(tmp_path):
    a_cm, g, fps = 25.0, 9.81, 240
    ref = read_reference(REF, "a_2.25in")
    t = np.arange(0, 120) / fps
    T = t * math.sqrt(2 * g / (a_cm * 0.01))
    front = np.interp(T, np.r_[0.0, ref[:, 0]], np.r_[1.0, ref[:, 1]]) * a_cm - 0.5
    err = surge_front_error(_fake_output(tmp_path, front, fps, spacing=1.0, mpu=0.01), study_dir=TESTS,
                            reference="data/martin_moyce_1952.csv", series="a_2.25in", column_width=a_cm, back_wall=0.0)
    assert err < 2e-3
