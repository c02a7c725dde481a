"""Property-based fuzzing of every reader, run in one child process under a memory limit (for
``test_reader_fuzz``).

Run as ``python -m tests.drivers.reader_fuzz_runner WORKDIR MEMORY_MB EXAMPLES [READER,...]``.
For each reader hypothesis draws inputs, random bytes or a sound file of the format mutated
(bytes flipped, truncated, a slice repeated, a header token replaced by a hostile one, a zip
member replaced by random JSON), and reads them. The only outcomes allowed are a result or one
of the project's input errors (:class:`~drivers.errors.DriverError`,
:class:`~recon.errors.ReconError`); anything else, or memory beyond the limit (a
:class:`MemoryError` under ``RLIMIT_AS``), is a failure, shrunk by hypothesis and reported with
its input saved. Before each read the input is written to ``WORKDIR/current-<reader>``, so when
native code kills the process the test can name the reader and keep the file. One JSON line per
reader goes to stdout.
"""

from __future__ import annotations

import io
import json
import resource
import sys
import traceback
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.calibration import (
    read_calibration,
    read_tip_calibration,
    write_calibration,
    write_tip_calibration,
)
from drivers.errors import DriverError, MissingDependencyError, ReaderCrashError, WorkerError
from drivers.scanning.base import read_scan
from drivers.scanning.pointcloud import write_scan
from drivers.tracking.canonical_csv import write_trace_csv
from drivers.tracking.readers import read_trace
from recon.errors import ReconError
from recon.inputs import Recording, Scan

#: Input errors that are no refusal of the input: a native crash, a package that is not
#: installed, a worker that died.
NOT_REFUSALS = (ReaderCrashError, MissingDependencyError, WorkerError)
#: Readers whose native library runs in a child of its own because it crashes on damaged files
#: (librealsense segfaults on a mutated bag; ezc3d on some C3D headers): for them a crash of
#: that child is the refusal (a 422 that says to record the file again), counted apart.
CRASH_CONTAINED = ("bag", "c3d")

#: Tokens a damaged or hostile header holds.
HOSTILE = [
    b"", b"-1", b"0", b"1e308", b"-1e308", b"99999999999999999999", b"nan", b"inf",
    b"x" * 1500, b"\xff\xfe", b"\x00", b",", b";", b"\n", b"\r\n", b'"', b"1" * 400,
]  # fmt: skip


def _helix(n: int = 120) -> tuple[np.ndarray, np.ndarray]:
    u = np.linspace(0.0, 4.0 * np.pi, n)
    points = np.column_stack([0.3 + 0.05 * np.cos(u), 0.1 + 0.05 * np.sin(u), 0.2 + 0.01 * u])
    return np.arange(n) / 120.0, points


def _file(write: Callable[[Path], None], folder: Path, name: str) -> bytes:
    path = folder / f"seed-{name}"
    write(path)
    return path.read_bytes()


def seeds(folder: Path) -> dict[str, tuple[str, bytes]]:
    """Sound files per reader: name -> (file name, content)."""
    from tests.drivers.test_reader_bounds import constant_depth_png, rgbd_zip
    from tests.drivers.test_rtde_csv import rtde_recording
    from tests.drivers.test_scan_readers import write_e57
    from tests.drivers.tracking_fixtures import helix, write_c3d, write_motive_csv

    t_s, points = _helix()
    recording = Recording(points_m=points, t_s=t_s)
    rng = np.random.default_rng(0)
    cloud_m = rng.uniform(-0.1, 0.1, (60, 3))
    cloud = Scan(points_m=cloud_m, normals=np.tile([0.0, 0.0, 1.0], (60, 1)))
    mt, mp, mq = helix(120)
    writers = {  # reader: (file name, writer of a sound file)
        "canonical_csv": ("trace.csv", lambda p: write_trace_csv(p, recording)),
        "motive_csv": ("take.csv", lambda p: write_motive_csv(p, mt, mp, mq)),
        "c3d": ("take.c3d", lambda p: write_c3d(p, ["tip"], points[:, None, :], 120.0)),
        "calibration": ("cal.json", lambda p: write_calibration(p, "T_base_tracker", np.eye(4))),
        "tip_calibration": ("tip.json", lambda p: write_tip_calibration(p, [0.0, 0.0, 0.12])),
        "e57": ("scan.e57", lambda p: write_e57(p, [(cloud_m, [1, 0, 0, 0], [0, 0, 0], None)])),
        "rgbd_zip": ("frames.zip", lambda p: rgbd_zip(p, 32, 24, [constant_depth_png(32, 24)])),
    }
    for suffix in ("ply", "pcd", "xyz", "xyzn", "pts"):
        writers[suffix] = (f"scan.{suffix}", lambda p: write_scan(p, cloud))
    out = {
        name: (filename, _file(write, folder, filename))
        for name, (filename, write) in writers.items()
    }
    out["rtde_csv"] = ("robot.csv", rtde_recording(t_s, points, np.zeros((len(t_s), 3))))
    out["bag"] = ("scan.bag", b"#ROSBAG V2.0\n" + rng.integers(0, 256, 400, np.uint8).tobytes())
    return out


def reader_for(name: str) -> Callable[[bytes, str], object]:
    if name in ("canonical_csv", "motive_csv", "rtde_csv", "c3d"):
        return lambda content, filename: read_trace(content, name=filename)
    if name == "calibration":
        return lambda content, filename: read_calibration(content, label=filename)
    if name == "tip_calibration":
        return lambda content, filename: read_tip_calibration(content, label=filename)
    return lambda content, filename: read_scan(content, name=filename)


@st.composite
def mutated(draw, seed: bytes) -> bytes:
    """``seed`` with one to four damages of the kinds a broken export or an attacker makes."""
    content = bytearray(seed)
    for _ in range(draw(st.integers(1, 4))):
        kind = draw(st.sampled_from(["flip", "truncate", "repeat", "token", "zip_member"]))
        at = draw(st.integers(0, max(len(content) - 1, 0)))
        if kind == "flip" and content:
            content[at] = draw(st.integers(0, 255))
        elif kind == "truncate":
            del content[at:]
        elif kind == "repeat":
            length = draw(st.integers(1, 64))
            content[at:at] = content[at : at + length] * draw(st.integers(1, 50))
        elif kind == "token":
            # Replace the word at ``at`` (up to the next separator) by a hostile token.
            end = at
            while end < len(content) and content[end : end + 1] not in (b" ", b",", b"\n"):
                end += 1
            content[at:end] = draw(st.sampled_from(HOSTILE))
        elif kind == "zip_member" and seed[:2] == b"PK":
            content = bytearray(_mutate_member(bytes(content), draw))
    return bytes(content)


def _mutate_member(content: bytes, draw) -> bytes:
    """A zip whose member (chosen by hypothesis) holds hostile JSON or a damaged image."""
    try:
        with zipfile.ZipFile(io.BytesIO(content)) as archive:
            members = {info.filename: archive.read(info) for info in archive.infolist()}
    except Exception:  # already damaged: leave it so
        return content
    if not members:
        return content
    name = draw(st.sampled_from(sorted(members)))
    if name.endswith(".json"):
        value = draw(
            st.recursive(
                st.none() | st.booleans() | st.floats() | st.integers() | st.text(max_size=20),
                lambda children: (
                    st.lists(children, max_size=6)
                    | st.dictionaries(st.text(max_size=8), children, max_size=6)
                ),
                max_leaves=20,
            )
        )
        if isinstance(value, dict) and draw(st.booleans()):
            value = {**json.loads(members[name]), **value}
        members[name] = json.dumps(value).encode()
    else:
        data = bytearray(members[name])
        data[draw(st.integers(0, len(data) - 1))] = draw(st.integers(0, 255))
        members[name] = bytes(data)
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as archive:
        for member, data in members.items():
            archive.writestr(member, data)
    return out.getvalue()


def fuzz(name: str, filename: str, seed: bytes, workdir: Path, examples: int) -> dict:
    """Draw ``examples`` inputs for one reader; the counts of outcomes, and the first failure."""
    read = reader_for(name)
    current = workdir / f"current-{name}"
    counts = {"read": 0, "refused": 0, "crashed in its child": 0}

    @settings(
        max_examples=examples,
        derandomize=True,  # the same inputs on every run: CI gives the same answer
        database=None,
        deadline=None,
        suppress_health_check=list(HealthCheck),
    )
    @given(st.one_of(st.binary(max_size=2048), mutated(seed)))
    def one(content: bytes) -> None:
        current.write_bytes(content)
        try:
            read(content, filename)
        except ReaderCrashError:
            if name not in CRASH_CONTAINED:
                raise
            counts["crashed in its child"] += 1
        except NOT_REFUSALS:
            raise  # a missing package, a dead worker: bugs
        except (DriverError, ReconError):
            counts["refused"] += 1
        else:
            counts["read"] += 1

    result = {"reader": name, **counts}
    try:
        one()
    except Exception as exc:  # hypothesis re-raises the shrunk failure
        failed = workdir / f"failure-{name}"
        failed.write_bytes(current.read_bytes())
        # The exception's class and message, not hypothesis's repr of a kilobyte-long input.
        cause = exc.__cause__ or exc.__context__ if isinstance(exc, AssertionError) else exc
        result["failure"] = f"{type(cause).__name__}: {str(cause)[:600]}"
        result["where"] = "".join(traceback.format_tb(cause.__traceback__)[-3:])[-1500:]
        result["input"] = str(failed)
    current.unlink(missing_ok=True)
    result.update(counts)
    return result


def main(workdir: str, memory_mb: str, examples: str, only: str = "") -> None:
    folder = Path(workdir)
    limit = int(float(memory_mb) * 2**20)
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    n = int(examples)
    for name, (filename, seed) in seeds(folder).items():
        if only and name not in only.split(","):
            continue
        # Readers that parse in a child of their own cost a process per input: fewer inputs.
        count = max(n // 8, 4) if name in ("c3d", "bag") else n
        print(json.dumps({"start": name}), flush=True)
        print(json.dumps(fuzz(name, filename, seed, folder, count)), flush=True)
    print(json.dumps({"peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))


if __name__ == "__main__":
    main(*sys.argv[1:])
