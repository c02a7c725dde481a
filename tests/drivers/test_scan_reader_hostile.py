"""Scan files that crashed Open3D's native readers, or failed with an exception no reader
should raise, are refused with an :class:`InputFileError` that says what to do (project issue
"Robustness").

A crash of native code takes the process with it (the service reads uploads in a child, so it
answered with a generic "the reader crashed"; the CLI died). Found by mutating the headers of
sound files: a PLY comment over 1024 bytes (RPly aborts), a PCD with ``normal_x`` but no
``normal_y`` (segmentation fault), a binary PCD without ``POINTS`` (a different cloud on every
read, or ``std::bad_alloc``); RGB-D zips with corrupt deflate data (``zlib.error``), a compression
method zipfile lacks (``NotImplementedError``) or a 2000-character member name (``OSError``);
intrinsics of thousands of digits (``OverflowError``); poses at 1e300 m, or frames 5 m apart
that share no voxel (Open3D's ``RuntimeError``).

All files are read by one child process (:mod:`tests.drivers.hostile_scan_runner`), so a crash
fails the test that names the file instead of killing the test run.
"""

from __future__ import annotations

import json
import random
import struct
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from tests.drivers.test_reader_bounds import POINTS, constant_depth_png, pcd, ply, rgbd_zip

REPO = Path(__file__).resolve().parents[2]
#: Errors a reader may answer bad input with (anything else is a bug).
REFUSALS = {"InputFileError", "InputTooLargeError"}


def read_all(paths: list[Path]) -> dict[str, dict]:
    """Outcome per file name; a file whose read killed the child is reported as a crash."""
    run = subprocess.run(
        [sys.executable, "-m", "tests.drivers.hostile_scan_runner", *map(str, paths)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
    )
    outcomes, started = {}, None
    for line in run.stdout.splitlines():
        record = json.loads(line)
        if "start" in record:
            started = record["start"]
        else:
            outcomes[Path(record["done"]).name] = record
            started = None
    if started is not None:
        outcomes[Path(started).name] = {
            "error": f"crash (exit {run.returncode})",
            "message": run.stderr[-2000:],
        }
    return outcomes


def write(folder: Path, name: str, content: bytes) -> Path:
    path = folder / name
    path.write_bytes(content)
    return path


# --------------------------------------------------------------------------- point clouds

PCD_ASCII_ROWS = b"".join(b"%d 0 1 0\n" % i for i in range(10))


def pcd_header(*, fields="x y z", size="4 4 4", type_="F F F", count="1 1 1", extra=""):
    return (
        f"VERSION .7\nFIELDS {fields}\nSIZE {size}\nTYPE {type_}\nCOUNT {count}\n{extra}"
    ).encode()


POINT_CLOUD_CASES = {
    # name: (content, fragment of the message)
    "long_comment.ply": (
        ply(10).replace(b"comment generated", b"comment " + b"x" * 2000 + b" generated"),
        "PLY header line of 2,0",
    ),
    "long_obj_info.ply": (
        ply(10).replace(b"comment", b"obj_info " + b"y" * 3000),
        "longer than the 1000 the PLY reader takes",
    ),
    "long_property_name.ply": (
        ply(10).replace(b"property float x", b"property float " + b"x" * 300),
        "name longer than 255 characters",
    ),
    "normal_x_alone.pcd": (
        pcd_header(fields="x y z normal_x", size="4 4 4 4", type_="F F F F", count="1 1 1 1")
        + b"WIDTH 10\nHEIGHT 1\nPOINTS 10\nDATA ascii\n"
        + PCD_ASCII_ROWS,
        "has normal_x but not normal_y, normal_z",
    ),
    "normal_x_alone_binary.pcd": (
        pcd_header(fields="x y z normal_x", size="4 4 4 4", type_="F F F F", count="1 1 1 1")
        + b"WIDTH 10\nHEIGHT 1\nPOINTS 10\nDATA binary\n"
        + np.zeros((10, 4), "<f4").tobytes(),
        "has normal_x but not normal_y, normal_z",
    ),
    "no_points_binary.pcd": (
        pcd_header() + b"DATA binary\n" + np.asarray(POINTS, "<f4").tobytes(),
        "without WIDTH and HEIGHT and POINTS",
    ),
    "no_points_line.pcd": (
        pcd_header() + b"WIDTH 10\nHEIGHT 1\nDATA binary\n" + np.asarray(POINTS, "<f4").tobytes(),
        "without POINTS",
    ),
    "points_disagree.pcd": (pcd(width=5), "declares POINTS 10 but WIDTH x HEIGHT = 5 x 1"),
    "no_x.pcd": (
        pcd_header(fields="a b c")
        + b"WIDTH 10\nHEIGHT 1\nPOINTS 10\nDATA ascii\n"
        + PCD_ASCII_ROWS,
        "no x, y and z fields",
    ),
    "size_3_float.pcd": (
        pcd_header(size="4 4 3") + b"WIDTH 10\nHEIGHT 1\nPOINTS 10\nDATA binary\n" + b"\0" * 110,
        "TYPE 'F' and SIZE 3, which PCD does not have",
    ),
    "size_huge.pcd": (
        pcd_header(size="4 4 99999999999999999999")
        + b"WIDTH 10\nHEIGHT 1\nPOINTS 10\nDATA ascii\n"
        + PCD_ASCII_ROWS,
        "which PCD does not have",
    ),
    "size_1e308.pcd": (
        pcd_header(size="4 4 1e308") + b"WIDTH 10\nHEIGHT 1\nPOINTS 10\nDATA ascii\n",
        "malformed PCD header (SIZE or COUNT)",
    ),
    "type_unknown.pcd": (
        pcd_header(type_="F F Q") + b"WIDTH 10\nHEIGHT 1\nPOINTS 10\nDATA binary\n" + b"\0" * 120,
        "TYPE 'Q'",
    ),
    "type_missing.pcd": (
        b"VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nCOUNT 1 1 1\nWIDTH 10\nHEIGHT 1\nPOINTS 10\n"
        b"DATA binary\n" + b"\0" * 120,
        "TYPE must give one entry per field",
    ),
    "count_negative.pcd": (
        pcd_header(count="1 1 -1") + b"WIDTH 10\nHEIGHT 1\nPOINTS 10\nDATA ascii\n",
        "a SIZE or COUNT below 1",
    ),
    "data_empty.pcd": (
        pcd_header() + b"WIDTH 10\nHEIGHT 1\nPOINTS 10\nDATA\n" + b"\0" * 120,
        "malformed PCD header (at 'DATA')",
    ),
}


def test_point_cloud_headers_that_crashed_open3d_are_refused_with_what_to_do(tmp_path):
    paths = [write(tmp_path, name, content) for name, (content, _) in POINT_CLOUD_CASES.items()]
    outcomes = read_all(paths)
    for name, (_, fragment) in POINT_CLOUD_CASES.items():
        got = outcomes[name]
        assert got["error"] == "InputFileError", (name, got)
        assert fragment in got["message"], (name, got["message"])
        assert "export the scan" in got["message"] or "shorten" in got["message"], name


def test_a_pcd_opening_with_long_comments_is_still_recognised(tmp_path):
    content = b"# " + b"c" * 5000 + b"\n" + pcd()
    outcomes = read_all([write(tmp_path, "commented.pcd", content)])
    assert outcomes["commented.pcd"] == {
        "done": str(tmp_path / "commented.pcd"),
        "error": None,
        "points": len(POINTS),
    }


# --------------------------------------------------------------------------- RGB-D


def intrinsics_zip(path: Path, intrinsics_text: str) -> Path:
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("intrinsics.json", intrinsics_text)
        archive.writestr("depth.png", constant_depth_png(64, 48))
    return path


def corrupt_deflate_zip(path: Path) -> Path:
    """A sound frames zip whose depth image's compressed bytes are overwritten (the CRC is
    never reached: inflating fails first)."""
    rgbd_zip(path, 64, 48, [constant_depth_png(64, 48)])
    data = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as archive:
        info = archive.getinfo("depth.png")
    start = info.header_offset + 30 + len(info.filename.encode()) + len(info.extra)
    data[start : start + 16] = b"\xff" * 16
    path.write_bytes(bytes(data))
    return path


def method_zip(path: Path, method: int) -> Path:
    """A stored frames zip whose depth member claims compression ``method`` (in its local
    header and its central directory entry)."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as archive:
        archive.writestr("intrinsics.json", json.dumps(_intrinsics(64, 48)))
        archive.writestr("depth.png", constant_depth_png(64, 48))
    data = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as archive:
        info = archive.getinfo("depth.png")
    struct.pack_into("<H", data, info.header_offset + 8, method)
    at = 0
    while (at := data.find(b"PK\x01\x02", at)) >= 0:
        name_length = struct.unpack_from("<H", data, at + 28)[0]
        if bytes(data[at + 46 : at + 46 + name_length]) == b"depth.png":
            struct.pack_into("<H", data, at + 10, method)
        at += 4
    path.write_bytes(bytes(data))
    return path


def _intrinsics(width: int, height: int) -> dict:
    return {
        "fx": 50.0,
        "fy": 50.0,
        "cx": width / 2,
        "cy": height / 2,
        "width": width,
        "height": height,
    }


def long_name_zip(path: Path) -> Path:
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("intrinsics.json", json.dumps(_intrinsics(64, 48)))
        archive.writestr("depth.png", constant_depth_png(64, 48))
        archive.writestr("n" * 2000 + ".txt", "notes")
    return path


def far_pose_zip(path: Path, distance_m: float) -> Path:
    """Two frames, the second's camera ``distance_m`` from the world origin."""
    pose = np.eye(4)
    pose[0, 3] = distance_m
    png = constant_depth_png(64, 48)
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("intrinsics.json", json.dumps(_intrinsics(64, 48)))
        archive.writestr("depth/000000.png", png)
        archive.writestr("depth/000001.png", png)
        archive.writestr(
            "poses.json", json.dumps({"000000": np.eye(4).tolist(), "000001": pose.tolist()})
        )
    return path


def test_rgbd_zips_that_raised_unexpected_exceptions_are_refused_with_what_to_do(tmp_path):
    huge = "1" + "0" * 3000  # JSON integer of 3001 digits: float() overflows
    cases = {
        "corrupt_deflate.zip": (
            corrupt_deflate_zip(tmp_path / "corrupt_deflate.zip"),
            "is corrupt: depth.png cannot be unpacked",
        ),
        "method_99.zip": (
            method_zip(tmp_path / "method_99.zip", 99),
            "(method 99); zip the folder again",
        ),
        "long_name.zip": (
            long_name_zip(tmp_path / "long_name.zip"),
            "a part longer than 255 bytes",
        ),
        "focal_digits.zip": (
            intrinsics_zip(
                tmp_path / "focal_digits.zip",
                json.dumps(_intrinsics(64, 48)).replace("50.0", huge, 1),
            ),
            "fx is a number too large for a float",
        ),
        "focal_huge.zip": (
            intrinsics_zip(
                tmp_path / "focal_huge.zip", json.dumps({**_intrinsics(64, 48), "fy": 1e300})
            ),
            "focal lengths must be positive pixels up to 1e+06",
        ),
        "apart.zip": (far_pose_zip(tmp_path / "apart.zip", 5.0), "gave no surface: the poses"),
        "far_pose.zip": (far_pose_zip(tmp_path / "far_pose.zip", 1e300), "m from the world origin"),
    }
    outcomes = read_all([path for path, _ in cases.values()])
    for name, (_, fragment) in cases.items():
        got = outcomes[name]
        assert got["error"] == "InputFileError", (name, got)
        assert fragment in got["message"], (name, got["message"])


# --------------------------------------------------------------------------- mutation fuzz

#: Header mutations: each replaces one header token by something a damaged or hostile file holds.
HOSTILE_TOKENS = [
    b"", b"-1", b"0", b"1e308", b"99999999999999999999", b"nan", b"x" * 1500, b"\xff\xfe",
    b"normal_x", b"list uchar int", b"binary", b"ascii", b"binary_compressed", b"F", b"U", b"8",
]  # fmt: skip


def mutants(seed: int, count: int) -> list[tuple[str, bytes]]:
    """``count`` files: sound PLY and PCD files with one to three header tokens replaced."""
    rng = random.Random(seed)
    sources = {
        "ply": ply(10),
        "ascii.ply": ply(10, fmt="ascii"),
        "pcd": pcd(),
        "ascii.pcd": pcd(data="ascii"),
    }
    files = []
    for i in range(count):
        kind = rng.choice(list(sources))
        content = sources[kind]
        split = content.index(b"end_header\n" if kind.endswith("ply") else b"\nDATA ") + 1
        header, body = content[:split], content[split:]
        tokens = header.replace(b"\n", b" \n ").split(b" ")
        for _ in range(rng.randint(1, 3)):
            spot = rng.randrange(len(tokens))
            if tokens[spot] != b"\n":
                tokens[spot] = rng.choice(HOSTILE_TOKENS)
        mutated = b" ".join(tokens).replace(b" \n ", b"\n")
        files.append((f"m{i:03d}.{kind.split('.')[-1]}", mutated + body))
    return files


def test_mutated_headers_are_read_or_refused_never_crash(tmp_path):
    files = mutants(seed=20261202, count=240)
    outcomes = read_all([write(tmp_path, name, content) for name, content in files])
    assert len(outcomes) == len(files)
    unexpected = {
        name: (got["error"], got.get("message", "")[:300])
        for name, got in outcomes.items()
        if got["error"] is not None and got["error"] not in REFUSALS
    }
    assert not unexpected, unexpected
    refused = sum(got["error"] is not None for got in outcomes.values())
    assert refused > len(files) // 2  # the mutations do damage: most files must be refused


@pytest.mark.parametrize("name", ["ply", "pcd"])
def test_the_mutation_sources_read(tmp_path, name):
    content = ply(10) if name == "ply" else pcd()
    outcomes = read_all([write(tmp_path, f"sound.{name}", content)])
    assert outcomes[f"sound.{name}"]["points"] == len(POINTS)
