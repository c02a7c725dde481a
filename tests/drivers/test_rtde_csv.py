"""Universal Robots RTDE recordings (UR's record.py, ur_rtde's file recording): the TCP pose read as
a trace, space- or comma-delimited, and the refusals that quote only part of the long header."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from drivers.errors import InputFileError
from drivers.tracking.readers import read_trace
from drivers.tracking.rtde_csv import read_rtde_csv
from tests.drivers.tracking_fixtures import helix

#: An output recipe like that of UR's example record configuration: (field, values per sample).
#: Vectors become ``field_0`` ... ``field_<n-1>`` in the header.
RECIPE = [
    ("timestamp", 1),
    ("target_q", 6),
    ("target_qd", 6),
    ("target_qdd", 6),
    ("target_current", 6),
    ("target_moment", 6),
    ("actual_q", 6),
    ("actual_qd", 6),
    ("actual_current", 6),
    ("joint_control_output", 6),
    ("actual_TCP_pose", 6),
    ("actual_TCP_speed", 6),
    ("actual_TCP_force", 6),
    ("target_TCP_pose", 6),
    ("target_TCP_speed", 6),
    ("actual_digital_input_bits", 1),
    ("joint_temperatures", 6),
    ("actual_execution_time", 1),
    ("robot_mode", 1),
    ("joint_mode", 6),
    ("safety_mode", 1),
    ("actual_tool_accelerometer", 3),
    ("speed_scaling", 1),
    ("target_speed_fraction", 1),
    ("actual_momentum", 1),
    ("actual_main_voltage", 1),
    ("actual_robot_voltage", 1),
    ("actual_robot_current", 1),
    ("actual_joint_voltage", 6),
    ("actual_digital_output_bits", 1),
    ("runtime_state", 1),
]


def header_names(recipe=RECIPE):
    return [f"{f}_{i}" if n > 1 else f for f, n in recipe for i in range(n)]


def rtde_recording(t, position, rotvec, delimiter=" ", recipe=RECIPE):
    """What the recorder writes: the header of the recipe's names, then one row per sample of
    Python's float text (csv.writer), the pose known, every other column some number."""
    names = header_names(recipe)
    rows = [delimiter.join(names)]
    for k in range(len(t)):
        values = []
        for field, n in recipe:
            if field == "timestamp":
                values.append(repr(float(t[k])))
            elif field == "actual_TCP_pose":
                values += [repr(float(v)) for v in (*position[k], *rotvec[k])]
            elif field.endswith(("_mode", "_bits", "_state")):
                values += [str(3 + k % 2)] * n
            else:
                values += [repr(0.001 * (k + i) - 0.5) for i in range(n)]
        rows.append(delimiter.join(values))
    return ("\n".join(rows) + "\n").encode()


@pytest.fixture
def arm():
    # 500 Hz from the controller's clock, which counts from its start-up.
    t, position, quat = helix(400, 500.0)
    return t + 5324.904, position, quat, Rotation.from_quat(quat).as_rotvec()


@pytest.mark.parametrize("delimiter", [" ", ","], ids=["record.py", "ur_rtde"])
def test_the_tcp_pose_is_read_as_a_trace(arm, delimiter):
    t, position, quat, rotvec = arm
    content = rtde_recording(t, position, rotvec, delimiter)
    header = content.split(b"\n")[0]
    assert header.startswith(b"timestamp" + delimiter.encode() + b"target_q_0")
    assert len(header) > 2000  # kilobytes of names, like the 2.7 KB one the issue quoted
    trace = read_trace(content, name="robot_data.csv")
    assert trace.format == "rtde" and trace.raw.meta["frame"] == "robot base"
    np.testing.assert_allclose(trace.recording.points_m, position, atol=1e-12)
    np.testing.assert_allclose(trace.recording.t_s, t, atol=1e-9)
    dot = np.abs(np.sum(trace.recording.orientations_xyzw * quat, axis=1))
    np.testing.assert_allclose(dot, 1.0, atol=1e-12)
    assert trace.raw.rate_hz == pytest.approx(500.0)
    assert trace.clean.report.n_invalid == 0 and len(trace.recording) == len(t)
    raw = read_rtde_csv(content, name="robot_data.csv")
    assert raw.delimiter == delimiter and raw.pose == "actual_TCP_pose"


def test_a_recording_without_the_tcp_pose_quotes_only_part_of_its_header(arm):
    t, position, rotvec = arm[0], arm[1], arm[3]
    recipe = [(f, n) for f, n in RECIPE if f != "actual_TCP_pose"]
    content = rtde_recording(t[:5], position[:5], rotvec[:5], recipe=recipe)
    with pytest.raises(InputFileError) as error:
        read_trace(content, name="robot_data.csv")
    message = str(error.value)
    assert message.startswith("robot_data.csv is an RTDE recording without the TCP pose")
    assert "'actual_TCP_pose_0', 'actual_TCP_pose_1'" in message
    assert "add actual_TCP_pose to the output recipe" in message
    assert f"Its {len(header_names(recipe))} columns: 'timestamp', 'target_q_0'" in message
    assert f"… and {len(header_names(recipe)) - 8} more" in message
    assert len(message) < 600 and "joint_temperatures" not in message


def test_a_torn_last_line_is_left_out_and_a_damaged_row_refused(arm):
    t, position, _quat, rotvec = arm
    content = rtde_recording(t[:50], position[:50], rotvec[:50])
    torn = content[:-200]  # the recorder stopped in the middle of the last row
    trace = read_rtde_csv(torn, name="r.csv")
    assert len(trace) == 49 and trace.torn_last_line
    np.testing.assert_allclose(trace.batch.position_m, position[:49], atol=1e-12)
    lines = content.decode().split("\n")
    lines[10] = " ".join(lines[10].split()[:-3])
    width = len(header_names())
    with pytest.raises(
        InputFileError, match=f"r.csv line 11 has {width - 3} cells where the header names {width}"
    ):
        read_rtde_csv("\n".join(lines).encode(), name="r.csv")
    cells = lines[20].split()
    cells[0] = cells[0].replace(".", "x", 1)
    lines[10], lines[20] = content.decode().split("\n")[10], " ".join(cells)
    with pytest.raises(InputFileError, match="r.csv line 21, column 'timestamp': '5324x.*not a"):
        read_rtde_csv("\n".join(lines).encode(), name="r.csv")
    repeated = content.decode().split("\n")
    repeated[30] = repeated[29]
    with pytest.raises(InputFileError, match=r"column 'timestamp' do not increase \(line 31\)"):
        read_rtde_csv("\n".join(repeated).encode(), name="r.csv")
    with pytest.raises(ValueError, match="unknown length unit"):
        read_rtde_csv(content, units="inch")
