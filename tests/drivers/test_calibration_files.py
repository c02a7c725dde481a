"""Calibration files: transforms and tip offsets, round trips and every bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from drivers.calibration import (
    read_calibration,
    read_tip_calibration,
    write_calibration,
    write_tip_calibration,
)
from drivers.errors import InputFileError


def _T():
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [5, 10, 80], degrees=True).as_matrix()
    T[:3, 3] = [0.4, 0.1, -0.05]
    return T


def test_transform_round_trip_with_residuals(tmp_path):
    path = tmp_path / "T.json"
    write_calibration(
        path, "T_base_tracker", _T(), residual_rms_m=2e-4, extra={"residuals_m": [1e-4, 3e-4]}
    )
    calibration = read_calibration(path, expect="T_base_tracker")
    np.testing.assert_allclose(calibration.matrix, _T(), atol=1e-12)
    assert calibration.residual_rms_m == 2e-4 and calibration.created
    assert json.loads(path.read_text())["residuals_m"] == [1e-4, 3e-4]


def test_transform_in_millimetres(tmp_path):
    T = _T()
    T_mm = T.copy()
    T_mm[:3, 3] *= 1000
    path = tmp_path / "T.json"
    path.write_text(json.dumps({"name": "T_base_tracker", "matrix": T_mm.tolist(), "units": "mm"}))
    np.testing.assert_allclose(read_calibration(path).matrix, T, atol=1e-12)


@pytest.mark.parametrize(
    "content, message",
    [
        ("", "not a readable JSON"),
        ("[1, 2]", "not a JSON object"),
        ('{"name": "T_base_tracker"}', 'no "matrix"'),
        (
            '{"name": "T_scan_tracker", "matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}',
            "T_base_tracker is needed",
        ),
        ('{"matrix": [[2,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}', "proper rotation"),
        ('{"matrix": [[1,0,0,NaN],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}', "finite"),
        ('{"matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]], "units": "ft"}', "unit"),
        (
            '{"matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]], "residual_rms_m": "small"}',
            "residual_rms_m.*non-negative number",
        ),
    ],
    ids=[
        "empty",
        "not-object",
        "no-matrix",
        "wrong-name",
        "not-rigid",
        "nan",
        "bad-units",
        "text-residual",
    ],
)
def test_transform_bad_input(tmp_path, content, message):
    path = tmp_path / "T.json"
    path.write_text(content)
    with pytest.raises(InputFileError, match=message):
        read_calibration(path, expect="T_base_tracker")


def test_missing_file(tmp_path):
    with pytest.raises(InputFileError, match="does not exist"):
        read_calibration(tmp_path / "nope.json")
    with pytest.raises(InputFileError, match="does not exist"):
        read_tip_calibration(tmp_path / "nope.json")


def test_tip_round_trip_and_units(tmp_path):
    path = tmp_path / "tip.json"
    write_tip_calibration(path, [0.004, -0.007, 0.142], rigid_body="pen", residual_rms_m=3e-4)
    tip = read_tip_calibration(path)
    np.testing.assert_allclose(tip.offset_m, [0.004, -0.007, 0.142])
    assert tip.rigid_body == "pen" and tip.residual_rms_m == 3e-4
    path.write_text(json.dumps({"name": "tip_offset", "offset": [4, -7, 142], "units": "mm"}))
    np.testing.assert_allclose(read_tip_calibration(path).offset_m, [0.004, -0.007, 0.142])
    with pytest.raises(ValueError, match="3 finite"):
        write_tip_calibration(path, [0.0, 0.1])


@pytest.mark.parametrize(
    "content, message",
    [
        ('{"name": "T_base_tracker", "matrix": []}', "not a tip calibration"),
        ('{"name": "tip_offset", "offset": [0, 0]}', "3 finite numbers"),
        ('{"name": "tip_offset", "offset": [0, NaN, 0.1]}', "3 finite numbers"),
        ('{"name": "tip_offset", "offset": [0, 0, 142]}', "are the units right"),
        ('{"name": "tip_offset", "offset": [0, 0, 0.1], "units": "inch"}', "unit"),
        ('{"name": "tip_offset", "offset": ["a", 0, 0.1]}', "tip.json"),
        ('{"name": "tip_offset", "offset": [0, 0, 0.1], "residual_rms_m": -1}', "non-negative"),
    ],
    ids=["transform-file", "short", "nan", "mm-as-m", "bad-units", "not-numbers", "neg-residual"],
)
def test_tip_bad_input(tmp_path, content, message):
    path = tmp_path / "tip.json"
    path.write_text(content)
    with pytest.raises(InputFileError, match=message):
        read_tip_calibration(path)
