"""RGB-D frames from a depth camera: one frame, or many with camera poses fused into one cloud.

What counts as one scan "file" (format ``rgbd``):

* a **folder**, or a **.zip** of one (uploads are single files), laid out as

  ::

      intrinsics.json          (or intrinsic.json, as Open3D's RealSense tools write it)
      depth.png                one frame, or
      depth/000000.png ...     several frames (sorted by name, numbers in names compared as numbers)
      trajectory.log           poses: an Open3D/Redwood log (per frame an index line whose first
                               number is the frame's place in name order, then 4 matrix rows), or
      poses.txt                TUM lines 'timestamp tx ty tz qx qy qz qw', matched within 20 ms
                               to depth images named by their timestamp, or
      poses.json               {"<depth file stem>": 4x4 T_world_camera, ...}  (one pose file)
      color/ color.png         optional; not read (a Scan has no colour channel)

  A zip may hold the layout at its top or inside a single folder.

* a **manifest** ``<name>.rgbd.json`` (or ``rgbd.json`` inside a folder or zip) naming the files,
  relative to its own folder::

      {"intrinsics": "intrinsics.json" | {"fx": ..., "fy": ..., "cx": ..., "cy": ...,
                                          "width": ..., "height": ...},
       "depth_scale": 1000,
       "frames": [{"depth": "depth/0.png", "color": "color/0.jpg",
                   "T_world_camera": [[...], [...], [...], [...]]}, ...]}

  A single frame may give ``depth``, ``color`` and ``T_world_camera`` at the top instead of
  ``frames``. An uploaded manifest cannot carry the files it names: upload a zip instead.

Depth images are 16-bit greyscale PNGs; a raw value ``d`` is ``d / depth_scale`` metres along the
camera's optical axis (default scale 1000: millimetres), 0 means no measurement. Intrinsics are
pinhole ``fx, fy, cx, cy`` in pixels for a ``width`` x ``height`` image, or Open3D's
PinholeCameraIntrinsic JSON (``width``, ``height``, ``intrinsic_matrix`` column-major); a
``depth_scale`` there (RealSense metadata) is used unless the manifest or the options give one
(options first, then the manifest, then the intrinsics file, then 1000).
Poses are ``T_world_camera`` (camera points into the scan frame). One frame without a pose is
read in the camera frame (x right, y down, z forward).

Several frames are fused with a TSDF (Open3D's VoxelBlockGrid) and the surface is extracted as
points with normals. Measured on 30 synthetic 640x480 frames (``tests/bench/test_bench_scans.py``)
against pose-transformed concatenation plus 2 mm voxel averaging: TSDF took 2.7 s against 7.1 s,
and with depth noise of 1 mm at 0.5 m it gave 0.34 mm RMS error on the workpiece against 2.1 mm
(concatenation keeps every noisy point and flying pixel). Without noise concatenation is exact to
the depth quantisation (0.19 mm RMS against 0.33 mm), so ``fusion="points"`` stays available, e.g.
for thin structures that a TSDF's truncation band would erase.

The pixels to decode are bounded before any image is decoded: the intrinsics' width x height per
frame (every depth PNG's header must match it, and is read without decoding) and that times the
number of frames, against ``max_frame_pixels`` and ``max_pixels``. A zip's size says nothing of
them: a 1.7 KB zip of one constant 8000 x 8000 PNG took 21 s and 3.4 GB to read, one of
30000 x 30000 failed after 46 s at 6 GB.
"""

from __future__ import annotations

import contextlib
import json
import lzma
import re
import tempfile
import zipfile
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any, ClassVar, Literal

import numpy as np
import open3d as o3d
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from scipy.spatial.transform import Rotation

from drivers.errors import InputFileError, InputTooLargeError, clipped
from drivers.scanning._native import check_image_file, open3d_message, quiet_open3d, read_image
from drivers.scanning.base import DROPPED_DEPTH, ReaderOptions, ScanFile, ScanReader
from drivers.scanning.limits import DEFAULT_MAX_FRAME_PIXELS, DEFAULT_MAX_PIXELS
from recon.arrays import FloatArray
from recon.inputs import Scan
from recon.transforms import RIGID_TOLERANCE, is_proper_rotation

#: Raw depth units per metre when nothing says otherwise (16-bit PNGs in millimetres).
DEFAULT_DEPTH_SCALE = 1000.0
#: A median depth closer than this is not something a depth camera measures (the closest-range
#: RealSense, the D405, starts at 7 cm): the depth scale is wrong.
MIN_PLAUSIBLE_DEPTH_M = 0.03
#: TUM trajectories are matched to images by timestamp within this (TUM's associate.py default).
TUM_MAX_DIFFERENCE_S = 0.02

MANIFEST_NAME = "rgbd.json"
MANIFEST_SUFFIX = ".rgbd.json"
INTRINSICS_NAMES = ("intrinsics.json", "intrinsic.json")
POSE_FILES = ("trajectory.log", "poses.txt", "poses.json")
_ZIP_JUNK = ("__MACOSX/", ".DS_Store")
#: Most members a frames zip may hold (a depth and a colour image per frame, 50k frames).
MAX_ZIP_MEMBERS = 100_000
#: Longest name of one folder or file inside a zip, in bytes (what Linux file systems allow).
MAX_ZIP_NAME_BYTES = 255
#: Largest focal length accepted (pixels): real depth cameras have 200-5000; beyond this the
#: intrinsics are in other units or corrupt.
MAX_FOCAL_PX = 1e6
#: Largest camera distance from the world origin accepted (m): frames of one workpiece lie
#: within metres of each other; beyond this a pose is in other units or corrupt.
MAX_CAMERA_DISTANCE_M = 1e3


class RGBDOptions(ReaderOptions):
    """Options of the RGB-D reader.

    Attributes
    ----------
    depth_scale : float or None
        Raw depth units per metre (1000 for millimetres). None: from the manifest or the
        intrinsics file, else 1000.
    depth_trunc_m : float
        Depths beyond this are left out (and counted): far measurements of a depth camera are
        noisy, and the workpiece is near.
    fusion : {"tsdf", "points"}
        How several frames become one cloud: TSDF fusion and surface extraction, or the frames'
        points concatenated and averaged per voxel.
    voxel_m : float
        TSDF voxel size, or the averaging voxel of ``points`` fusion.
    sdf_trunc_voxels : float
        TSDF truncation distance in voxels; it must exceed the depth noise.
    min_observations : int
        TSDF voxels seen by fewer frames than this are not extracted (capped at the number of
        frames), which removes one-off outliers.
    max_unpacked_mb : float
        Largest total size a zip may unpack to (a guard against zip bombs).
    max_frame_pixels : int
        Largest depth image (width x height, from the intrinsics and each PNG's header), checked
        before anything is decoded.
    max_pixels : int
        Largest number of pixels over all frames, checked before anything is decoded.
    """

    kind: Literal["rgbd"] = "rgbd"
    depth_scale: float | None = Field(None, gt=0)
    depth_trunc_m: float = Field(3.0, gt=0)
    fusion: Literal["tsdf", "points"] = "tsdf"
    # Below 0.5 mm the voxels outnumber what a depth camera resolves and memory explodes.
    voxel_m: float = Field(0.002, ge=5e-4, le=0.1)
    sdf_trunc_voxels: float = Field(4.0, ge=1.0, le=32.0)
    min_observations: int = Field(3, ge=1)
    max_unpacked_mb: float = Field(4096.0, gt=0)
    max_frame_pixels: int = Field(DEFAULT_MAX_FRAME_PIXELS, gt=0)
    max_pixels: int = Field(DEFAULT_MAX_PIXELS, gt=0)


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of a depth image.

    Attributes
    ----------
    width, height : int
        Image size, pixels.
    fx, fy : float
        Focal lengths, pixels.
    cx, cy : float
        Principal point, pixels (from the centre of the top-left pixel).
    depth_scale : float or None
        Raw depth units per metre, if the intrinsics file states it.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    depth_scale: float | None = None

    def to_open3d(self) -> o3d.camera.PinholeCameraIntrinsic:
        return o3d.camera.PinholeCameraIntrinsic(
            self.width, self.height, self.fx, self.fy, self.cx, self.cy
        )

    @property
    def matrix(self) -> FloatArray:
        """The 3x3 camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class Frame:
    """One depth image of a frame set and its camera pose (None: not given)."""

    depth: Path
    name: str
    T_world_camera: FloatArray | None = None
    color: Path | None = None


@dataclass(frozen=True)
class FrameSet:
    """RGB-D frames to read: intrinsics, frames in order, and where the depth scale came from."""

    intrinsics: Intrinsics
    frames: tuple[Frame, ...]
    depth_scale: float | None = None
    layout: str = ""
    notes: tuple[str, ...] = field(default=())


# --------------------------------------------------------------------------- intrinsics, poses


def parse_intrinsics(value: Any, label: str) -> Intrinsics:
    """Intrinsics from a decoded JSON object (plain ``fx, fy, cx, cy`` or Open3D's layout).

    Raises
    ------
    InputFileError
        Not an object, missing fields, non-numbers, NaN, or values no camera has.
    """
    if not isinstance(value, dict):
        raise InputFileError(f"{label} must be a JSON object with the camera intrinsics")
    if "intrinsic_matrix" in value:
        m = _numbers(value["intrinsic_matrix"], label, "intrinsic_matrix", 9)
        # Open3D writes K column-major: [fx, 0, 0, 0, fy, 0, cx, cy, 1]; accept row-major too.
        if m[2] == 0 and m[5] == 0 and m[8] == 1:
            fx, fy, cx, cy = m[0], m[4], m[6], m[7]
        elif m[6] == 0 and m[7] == 0 and m[8] == 1:
            fx, fy, cx, cy = m[0], m[4], m[2], m[5]
        else:
            raise InputFileError(
                f"{label}: intrinsic_matrix {m} is not a pinhole camera matrix "
                "(expected [fx, 0, 0, 0, fy, 0, cx, cy, 1], column-major as Open3D writes it)"
            )
        required: tuple[str, ...] = ("width", "height")
    else:
        required = ("fx", "fy", "cx", "cy", "width", "height")
    missing = [key for key in required if key not in value]
    if missing:
        raise InputFileError(
            f"{label} lacks {', '.join(missing)}; it needs fx, fy, cx, cy (pixels), width and "
            "height, or Open3D's width, height and intrinsic_matrix"
        )
    if "intrinsic_matrix" not in value:
        fx, fy, cx, cy = (_number(value[key], label, key) for key in ("fx", "fy", "cx", "cy"))
    width = _number(value["width"], label, "width")
    height = _number(value["height"], label, "height")
    if not (width == int(width) and height == int(height) and width > 0 and height > 0):
        raise InputFileError(
            f"{label}: width and height must be positive whole pixels, got {width} x {height}"
        )
    width, height = int(width), int(height)
    if not (0 < fx <= MAX_FOCAL_PX and 0 < fy <= MAX_FOCAL_PX):
        raise InputFileError(
            f"{label}: focal lengths must be positive pixels up to {MAX_FOCAL_PX:g}, got {fx:g}, "
            f"{fy:g}; check that the intrinsics are in pixels"
        )
    if not (0 <= cx <= width and 0 <= cy <= height):
        raise InputFileError(
            f"{label}: the principal point ({cx}, {cy}) lies outside the {width} x {height} "
            "image; check that the intrinsics belong to this image size"
        )
    scale = value.get("depth_scale")
    if scale is not None:
        scale = _number(scale, label, "depth_scale")
        if scale <= 0:
            # Open3D's metadata JSON writes 0 when it does not know the scale.
            scale = None
    return Intrinsics(width, height, fx, fy, cx, cy, scale)


def _number(value: Any, label: str, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputFileError(f"{label}: {key} must be a number, got {clipped(repr(value), 40)}")
    try:
        number = float(value)  # JSON integers may have thousands of digits
    except OverflowError:
        raise InputFileError(
            f"{label}: {key} is a number too large for a float; give a finite number"
        ) from None
    if not np.isfinite(number):
        raise InputFileError(f"{label}: {key} is {number}; give a finite number")
    return number


def _numbers(value: Any, label: str, key: str, count: int) -> list[float]:
    if not isinstance(value, list) or len(value) != count:
        raise InputFileError(f"{label}: {key} must be a list of {count} numbers")
    return [_number(v, label, f"{key}[{i}]") for i, v in enumerate(value)]


def check_pose(value: Any, label: str) -> FloatArray:
    """A 4x4 rigid transform from nested lists, checked.

    Raises
    ------
    InputFileError
        Wrong shape, NaN, a last row other than (0, 0, 0, 1), or a rotation part that is not a
        rotation (a scaled or mirrored matrix is a wrong export, not a camera pose).
    """
    try:
        T = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputFileError(f"{label} must be a 4x4 matrix of numbers") from None
    if T.shape != (4, 4):
        raise InputFileError(f"{label} must be a 4x4 matrix, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise InputFileError(f"{label} has NaN or infinite values")
    if np.linalg.norm(T[:3, 3]) > MAX_CAMERA_DISTANCE_M:
        raise InputFileError(
            f"{label} puts the camera {np.linalg.norm(T[:3, 3]):.3g} m from the world origin, "
            f"more than {MAX_CAMERA_DISTANCE_M:g} m: give the translation in metres"
        )
    if not np.allclose(T[3], [0, 0, 0, 1], rtol=0.0, atol=RIGID_TOLERANCE):
        raise InputFileError(f"{label} has last row {T[3].tolist()}, not [0, 0, 0, 1]")
    # The project's one rigidity tolerance (see recon.transforms.RIGID_TOLERANCE).
    if not is_proper_rotation(T[:3, :3]):
        raise InputFileError(
            f"{label}: the rotation part is not a rotation (scaled, sheared or mirrored); give "
            "T_world_camera as a rigid transform"
        )
    return T


def read_open3d_log(path: Path, n_frames: int) -> dict[int, FloatArray]:
    """Camera poses from an Open3D/Redwood ``.log`` trajectory: frame index -> T_world_camera.

    Each entry is a line whose first number is the frame index, then four rows of the 4x4
    camera-to-world matrix.
    """
    label = path.name
    rows = [line.split() for line in _text(path).splitlines() if line.strip()]
    if not rows:
        raise InputFileError(f"{label} is empty; it should hold one pose per depth image")
    if len(rows) % 5:
        raise InputFileError(
            f"{label} has {len(rows)} non-empty lines; an Open3D log has 5 per frame (an index "
            "line and four matrix rows): it is truncated or not a trajectory log"
        )
    poses: dict[int, FloatArray] = {}
    for start in range(0, len(rows), 5):
        head = rows[start]
        try:
            index = int(head[0])
            matrix = [[float(v) for v in row] for row in rows[start + 1 : start + 5]]
        except (ValueError, IndexError):
            raise InputFileError(
                f"{label}: entry at line {start + 1} is not an index line and four rows of numbers"
            ) from None
        if any(len(row) != 4 for row in matrix):
            raise InputFileError(f"{label}: the matrix after line {start + 1} is not 4x4")
        if index in poses:
            raise InputFileError(f"{label} gives frame {index} twice")
        if not 0 <= index < n_frames:
            raise InputFileError(
                f"{label} has a pose for frame {index}, but there are {n_frames} depth images "
                f"(indices 0 to {n_frames - 1})"
            )
        poses[index] = check_pose(matrix, f"{label}, frame {index}")
    return poses


def read_tum(path: Path) -> tuple[FloatArray, FloatArray]:
    """A TUM trajectory: timestamps (s) and T_world_camera of each line.

    Lines are ``timestamp tx ty tz qx qy qz qw`` (quaternion scalar last); ``#`` starts a comment.
    """
    label = path.name
    stamps, poses = [], []
    for number, line in enumerate(_text(path).splitlines(), start=1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        try:
            values = [float(v) for v in text.replace(",", " ").split()]
        except ValueError:
            raise InputFileError(f"{label} line {number}: not a list of numbers") from None
        if len(values) != 8:
            raise InputFileError(
                f"{label} line {number} has {len(values)} values; TUM lines are "
                "'timestamp tx ty tz qx qy qz qw'"
            )
        if not np.all(np.isfinite(values)):
            raise InputFileError(f"{label} line {number} has NaN or infinite values")
        q = np.array(values[4:])
        if np.linalg.norm(q) < 1e-9:
            raise InputFileError(f"{label} line {number} has a zero quaternion")
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat(q / np.linalg.norm(q), scalar_first=False).as_matrix()
        T[:3, 3] = values[1:4]
        stamps.append(values[0])
        poses.append(T)
    if not poses:
        raise InputFileError(f"{label} holds no poses")
    return np.array(stamps), np.array(poses)


def _text(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise InputFileError(f"{path.name} is not a text file") from None


def _json(path: Path, label: str) -> Any:
    if not path.is_file():
        raise InputFileError(f"{label} does not exist or is not a file")
    text = _text(path)
    if not text.strip():
        raise InputFileError(f"{label} is empty")
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputFileError(
            f"{label} is not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})"
        ) from None


# --------------------------------------------------------------------------- layouts


class _ManifestFrame(BaseModel):
    model_config = ConfigDict(extra="forbid")

    depth: str
    color: str | None = None
    T_world_camera: list[list[float]] | None = None


class _Manifest(BaseModel):
    model_config = ConfigDict(extra="forbid")

    intrinsics: str | dict[str, Any]
    depth_scale: float | None = None
    frames: list[_ManifestFrame] | None = None
    depth: str | None = None
    color: str | None = None
    T_world_camera: list[list[float]] | None = None


def load_manifest(path: Path, label: str | None = None) -> FrameSet:
    """The frame set a manifest (``*.rgbd.json``) describes; files relative to its folder."""
    label = label or path.name
    raw = _json(path, label)
    try:
        manifest = _Manifest.model_validate(raw)
    except ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in err['loc']) or 'manifest'}: {err['msg']}"
            for err in exc.errors()
        )
        raise InputFileError(f"{label} is not a valid RGB-D manifest: {problems}") from None
    root = path.parent
    if (manifest.frames is None) == (manifest.depth is None):
        raise InputFileError(
            f"{label} must give either 'frames' (a list) or one frame's 'depth', not "
            + ("both" if manifest.frames is not None else "neither")
        )
    entries = manifest.frames
    if entries is None:
        entries = [
            _ManifestFrame(
                depth=manifest.depth, color=manifest.color, T_world_camera=manifest.T_world_camera
            )
        ]
    elif manifest.color is not None or manifest.T_world_camera is not None:
        raise InputFileError(f"{label}: with 'frames', give 'color' and poses per frame")
    if not entries:
        raise InputFileError(f"{label} lists no frames")
    if isinstance(manifest.intrinsics, str):
        intr_path = _inside(root, manifest.intrinsics, label)
        intrinsics = parse_intrinsics(_json(intr_path, manifest.intrinsics), manifest.intrinsics)
    else:
        intrinsics = parse_intrinsics(manifest.intrinsics, f"{label} intrinsics")
    if manifest.depth_scale is not None and not (
        np.isfinite(manifest.depth_scale) and manifest.depth_scale > 0
    ):
        raise InputFileError(f"{label}: depth_scale must be a positive number")
    frames = []
    for i, entry in enumerate(entries):
        pose = None
        if entry.T_world_camera is not None:
            pose = check_pose(entry.T_world_camera, f"{label}, T_world_camera of frame {i}")
        frames.append(
            Frame(
                depth=_inside(root, entry.depth, label),
                name=entry.depth,
                T_world_camera=pose,
                color=None if entry.color is None else _inside(root, entry.color, label),
            )
        )
    return FrameSet(
        intrinsics=intrinsics,
        frames=tuple(frames),
        depth_scale=manifest.depth_scale,
        layout=f"manifest {label}",
    )


def _inside(root: Path, relative: str, label: str) -> Path:
    """``relative`` resolved under ``root``; names that climb out of it are refused."""
    candidate = (root / relative).resolve()
    if PurePosixPath(relative).is_absolute() or not candidate.is_relative_to(root.resolve()):
        raise InputFileError(
            f"{label} names {relative!r}, which is outside its folder; give paths relative to "
            "the manifest, inside its folder"
        )
    return candidate


def _natural_key(name: str) -> list[int | str]:
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name)]


def load_folder(root: Path, label: str) -> FrameSet:
    """The frame set of a folder (a manifest in it, or the conventional layout)."""
    manifests = sorted(
        p for p in root.iterdir() if p.is_file() and p.name.lower().endswith(MANIFEST_NAME)
    )
    if len(manifests) > 1:
        raise InputFileError(
            f"{label} holds {len(manifests)} manifests ({', '.join(p.name for p in manifests)});"
            " keep one"
        )
    if manifests:
        return load_manifest(manifests[0], f"{label}/{manifests[0].name}")
    found = [root / name for name in INTRINSICS_NAMES if (root / name).is_file()]
    if not found:
        raise InputFileError(
            f"{label} has no intrinsics.json (nor a rgbd.json manifest); an RGB-D folder needs "
            "intrinsics.json with fx, fy, cx, cy, width, height and depth.png or depth/*.png"
        )
    if len(found) > 1:
        raise InputFileError(f"{label} has both intrinsics.json and intrinsic.json; keep one")
    intrinsics = parse_intrinsics(_json(found[0], found[0].name), found[0].name)
    depth_dir = root / "depth"
    if depth_dir.is_dir():
        files = sorted(
            (p for p in depth_dir.iterdir() if p.is_file() and p.suffix.lower() == ".png"),
            key=lambda p: _natural_key(p.name),
        )
        if not files:
            raise InputFileError(f"{label}/depth holds no .png depth images")
        frames = [Frame(depth=p, name=f"depth/{p.name}") for p in files]
    elif (root / "depth.png").is_file():
        frames = [Frame(depth=root / "depth.png", name="depth.png")]
    else:
        raise InputFileError(f"{label} has no depth.png and no depth/ folder of .png depth images")
    pose_files = [root / name for name in POSE_FILES if (root / name).is_file()]
    if len(pose_files) > 1:
        raise InputFileError(
            f"{label} has several pose files ({', '.join(p.name for p in pose_files)}); keep one"
        )
    notes: tuple[str, ...] = ()
    if pose_files:
        frames = _attach_poses(frames, pose_files[0])
    elif len(frames) > 1:
        raise InputFileError(
            f"{label} has {len(frames)} depth images but no camera poses; add trajectory.log "
            "(Open3D log), poses.txt (TUM) or poses.json with T_world_camera of every frame"
        )
    return FrameSet(
        intrinsics=intrinsics,
        frames=tuple(frames),
        depth_scale=None,
        layout=f"folder {label}",
        notes=notes,
    )


def _attach_poses(frames: list[Frame], pose_file: Path) -> list[Frame]:
    name = pose_file.name
    if name == "trajectory.log":
        by_index = read_open3d_log(pose_file, len(frames))
        poses = []
        for i, frame in enumerate(frames):
            if i not in by_index:
                raise InputFileError(
                    f"no pose for frame {frame.name} (index {i}) in {name}; every depth image "
                    "needs one"
                )
            poses.append(by_index[i])
    elif name == "poses.txt":
        stamps, matrices = read_tum(pose_file)
        poses = []
        for frame in frames:
            try:
                t = float(frame.depth.stem)
            except ValueError:
                raise InputFileError(
                    f"{name} (TUM) poses are matched to depth images by the timestamp in their "
                    f"names (e.g. 1305031102.160407.png), but {frame.name} has none; rename the "
                    "images or use trajectory.log"
                ) from None
            nearest = int(np.argmin(np.abs(stamps - t)))
            if abs(stamps[nearest] - t) > TUM_MAX_DIFFERENCE_S:
                raise InputFileError(
                    f"no pose for frame {frame.name} in {name}: the nearest timestamp is "
                    f"{abs(stamps[nearest] - t) * 1e3:.0f} ms away (at most "
                    f"{TUM_MAX_DIFFERENCE_S * 1e3:.0f} ms)"
                )
            poses.append(matrices[nearest])
    else:
        mapping = _json(pose_file, name)
        if not isinstance(mapping, dict):
            raise InputFileError(
                f"{name} must be an object mapping depth image names to 4x4 T_world_camera"
            )
        poses = []
        for frame in frames:
            key = next((k for k in (frame.depth.stem, frame.depth.name) if k in mapping), None)
            if key is None:
                raise InputFileError(
                    f"no pose for frame {frame.name} in {name}; add '{frame.depth.stem}': "
                    "T_world_camera (4x4)"
                )
            poses.append(check_pose(mapping[key], f"{name}, frame {key}"))
    return [
        Frame(depth=f.depth, name=f.name, T_world_camera=T, color=f.color)
        for f, T in zip(frames, poses, strict=True)
    ]


def extract_zip(
    path: Path,
    dest: Path,
    label: str,
    *,
    max_unpacked_mb: float,
    limit_source: str = "the reader option max_unpacked_mb",
) -> Path:
    """Unpack a zip of an RGB-D folder safely; return the folder holding the layout.

    Parameters
    ----------
    path, dest : Path
        The zip, and the folder to unpack it into.
    label : str
        The zip's name in messages.
    max_unpacked_mb : float
        Largest total size of its members (as its directory states; reading stops there too).
    limit_source : str
        What sets ``max_unpacked_mb``, named in the message refusing a larger zip.

    Raises
    ------
    InputFileError
        Not a zip, truncated or corrupt, unsafe member names, or no layout.
    InputTooLargeError
        Members larger than ``max_unpacked_mb`` in all.
    """
    try:
        archive = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError):
        raise InputFileError(f"{label} is not a zip archive, or it is truncated") from None
    with archive:
        members = [
            info
            for info in archive.infolist()
            if not info.is_dir() and not any(junk in info.filename for junk in _ZIP_JUNK)
        ]
        if not members:
            raise InputFileError(f"{label} is an empty zip archive")
        total = sum(info.file_size for info in members)
        if total > max_unpacked_mb * 2**20:
            raise InputTooLargeError(
                f"{label} unpacks to {total / 2**20:.0f} MiB, more than the "
                f"{max_unpacked_mb:.0f} MiB allowed ({limit_source}); send fewer frames",
                limit="unpacked",
                value=max_unpacked_mb * 2**20,
                setting=limit_source,
            )
        if len(members) > MAX_ZIP_MEMBERS:
            raise InputTooLargeError(
                f"{label} holds {len(members):,} files, more than the {MAX_ZIP_MEMBERS:,} a "
                "frames zip may hold; send fewer frames",
                limit="members",
                value=MAX_ZIP_MEMBERS,
                setting="drivers.scanning.rgbd.MAX_ZIP_MEMBERS",
            )
        for info in members:
            _unpack_member(archive, info, dest, label)
    root = dest
    for _ in range(3):  # "zip the folder" usually nests the layout one level down
        if _has_layout(root):
            return root
        entries = [p for p in root.iterdir() if not p.name.startswith(".")]
        if len(entries) == 1 and entries[0].is_dir():
            root = entries[0]
        else:
            break
    if _has_layout(root):
        return root
    raise InputFileError(
        f"{label} holds no RGB-D frames: expected intrinsics.json with depth.png or depth/*.png "
        "(or a rgbd.json manifest) at its top or in its single folder"
    )


def _unpack_member(archive: zipfile.ZipFile, info: zipfile.ZipInfo, dest: Path, label: str) -> None:
    """Unpack one member under ``dest``; every way it can fail is an :class:`InputFileError`."""
    shown = clipped(info.filename)
    parts = PurePosixPath(info.filename.replace("\\", "/"))
    if parts.is_absolute() or ".." in parts.parts:
        raise InputFileError(f"{label} holds an unsafe member name {shown!r}")
    if any(
        len(part.encode("utf-8", "surrogateescape")) > MAX_ZIP_NAME_BYTES for part in parts.parts
    ):
        raise InputFileError(
            f"{label} holds a member whose name has a part longer than {MAX_ZIP_NAME_BYTES} "
            f"bytes ({shown!r}); rename it and zip the folder again"
        )
    target = dest.joinpath(*parts.parts)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        with archive.open(info) as src, target.open("wb") as out:
            while chunk := src.read(1 << 20):
                out.write(chunk)
    except (NotImplementedError, RuntimeError) as exc:
        if info.flag_bits & 0x1:  # encrypted members need a password
            raise InputFileError(
                f"{label}: {shown} is encrypted; zip the folder again without a password"
            ) from None
        # A compression method zipfile does not know, or whose module is missing.
        raise InputFileError(
            f"{label}: {shown} is compressed with a method this reader cannot unpack "
            f"(method {info.compress_type}: {exc}); zip the folder again with deflate or no "
            "compression"
        ) from None
    except (zipfile.BadZipFile, zlib.error, lzma.LZMAError, OSError, EOFError) as exc:
        raise InputFileError(f"{label} is corrupt: {shown} cannot be unpacked ({exc})") from None


def _has_layout(root: Path) -> bool:
    return any(
        p.is_file() and (p.name.lower().endswith(MANIFEST_NAME) or p.name in INTRINSICS_NAMES)
        for p in root.iterdir()
    )


# --------------------------------------------------------------------------- depth to points


def read_depth(path: Path, intrinsics: Intrinsics, label: str) -> np.ndarray:
    """A 16-bit depth image as an array of shape (height, width), raw units.

    Raises
    ------
    InputFileError
        Missing, truncated or corrupt file, not a 16-bit greyscale PNG, or a size other than the
        intrinsics'.
    """
    info = check_image_file(path, label)
    if info.kind != "png" or info.bit_depth != 16 or info.channels != 1:
        what = (
            "a JPEG"
            if info.kind == "jpeg"
            else f"a {info.bit_depth}-bit PNG with {info.channels} channel(s)"
        )
        raise InputFileError(
            f"{label} is {what}; depth must be a 16-bit greyscale PNG (raw units, 0 = no depth)"
        )
    if (info.width, info.height) != (intrinsics.width, intrinsics.height):
        raise InputFileError(
            f"{label} is {info.width} x {info.height} pixels but the intrinsics are for "
            f"{intrinsics.width} x {intrinsics.height}; use the intrinsics of the depth stream"
        )
    depth = np.asarray(read_image(path, label))
    if depth.dtype != np.uint16 or depth.shape != (intrinsics.height, intrinsics.width):
        raise InputFileError(f"{label} decoded to {depth.dtype} {depth.shape}, not a depth image")
    return depth


def depth_median_m(raw: np.ndarray, depth_scale: float) -> float | None:
    """Median of the measured depths (non-zero pixels) in metres, or None if there are none."""
    measured = raw[raw > 0]
    if measured.size == 0:
        return None
    return float(np.median(measured)) / depth_scale


def check_depth_scale(
    median_m: float, depth_scale: float, depth_trunc_m: float, label: str
) -> None:
    """Refuse a depth scale that puts the scene where no depth camera sees it.

    A scale off by 1000 (metres read as millimetres or the reverse) moves the median depth out of
    ``[MIN_PLAUSIBLE_DEPTH_M, depth_trunc_m]``; the message names the scale that would fit.

    Raises
    ------
    InputFileError
    """
    raw_median = median_m * depth_scale
    if median_m > depth_trunc_m:
        hint = ""
        if raw_median / DEFAULT_DEPTH_SCALE <= depth_trunc_m:
            hint = (
                f"; if the PNG holds millimetres, use depth_scale {DEFAULT_DEPTH_SCALE:g} (median "
                f"{raw_median / DEFAULT_DEPTH_SCALE:.3g} m)"
            )
        raise InputFileError(
            f"{label}: with depth_scale {depth_scale:g} (raw units per metre) the median depth "
            f"is {median_m:.4g} m, beyond depth_trunc_m {depth_trunc_m:g}: the depth scale is "
            f"wrong or depth_trunc_m too small{hint}"
        )
    if median_m < MIN_PLAUSIBLE_DEPTH_M:
        suggestion = depth_scale / 1000.0
        raise InputFileError(
            f"{label}: with depth_scale {depth_scale:g} (raw units per metre) the median depth "
            f"is {median_m * 1e3:.3g} mm, closer than depth cameras measure: the depth scale is "
            f"wrong (perhaps {suggestion:g}; 16-bit PNGs in millimetres need "
            f"{DEFAULT_DEPTH_SCALE:g})"
        )


def truncate_depth(
    raw: np.ndarray, *, depth_scale: float, depth_trunc_m: float
) -> tuple[np.ndarray, int]:
    """Zero the depths beyond ``depth_trunc_m``; return the result and how many there were.

    Done here rather than by Open3D, which also drops depths equal to its truncation and does
    not say how many it dropped.
    """
    beyond = raw > depth_trunc_m * depth_scale
    return np.where(beyond, 0, raw).astype(raw.dtype), int(np.count_nonzero(beyond))


def backproject(
    raw: np.ndarray,
    intrinsics: Intrinsics,
    *,
    depth_scale: float,
    T_world_camera: FloatArray | None = None,
) -> FloatArray:
    """Points of a depth image, with Open3D.

    Parameters
    ----------
    raw : ndarray of shape (H, W), uint16
        Raw depth, 0 = no measurement (already truncated, see :func:`truncate_depth`).
    intrinsics : Intrinsics
    depth_scale : float
        Raw units per metre.
    T_world_camera : ndarray of shape (4, 4), optional
        Camera pose; identity (camera frame) if omitted.

    Returns
    -------
    ndarray of shape (N, 3), metres
        One point per non-zero pixel, in row-major pixel order.
    """
    # Open3D takes the extrinsic as world-to-camera.
    extrinsic = np.eye(4) if T_world_camera is None else np.linalg.inv(T_world_camera)
    with quiet_open3d():
        cloud = o3d.geometry.PointCloud.create_from_depth_image(
            o3d.geometry.Image(np.ascontiguousarray(raw).data),
            intrinsics.to_open3d(),
            extrinsic,
            depth_scale=depth_scale,
            depth_trunc=np.inf,
            stride=1,
            project_valid_depth_only=True,
        )
    return np.asarray(cloud.points, dtype=np.float64)


@contextlib.contextmanager
def _open3d_refusal(doing: str) -> Iterator[None]:
    """Open3D's fusion raises RuntimeError on input it cannot use (poses far out, frames that
    observe no voxel); that is a property of the frames, said as such."""
    try:
        yield
    except RuntimeError as exc:
        raise InputFileError(
            f"the TSDF fusion failed {doing} ({open3d_message(exc)}): check that the poses are "
            "T_world_camera in metres and that the frames see the workpiece, or use fusion 'points'"
        ) from None


class _TSDF:
    """Open3D's tensor VoxelBlockGrid on the CPU (the legacy ScalableTSDFVolume extracted
    nothing from our synthetic frames in open3d 0.20)."""

    def __init__(self, intrinsics: Intrinsics, options: RGBDOptions) -> None:
        self.options = options
        self.device = o3d.core.Device("CPU:0")
        # block_count is the hash map's initial capacity; it grows on the CPU as needed.
        self.grid = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight"),
            attr_dtypes=(o3d.core.float32, o3d.core.float32),
            attr_channels=(o3d.core.SizeVector([1]), o3d.core.SizeVector([1])),
            voxel_size=options.voxel_m,
            block_resolution=8,
            block_count=10000,
            device=self.device,
        )
        self.K = o3d.core.Tensor(intrinsics.matrix, o3d.core.float64, self.device)
        self.n_frames = 0

    def integrate(self, raw: np.ndarray, depth_scale: float, T_world_camera: FloatArray) -> None:
        """Integrate a truncated depth image (see :func:`truncate_depth`)."""
        # from_numpy shares the copy's memory, of raw's own dtype (uint16 or float32 depth).
        depth = o3d.t.geometry.Image(o3d.core.Tensor.from_numpy(np.ascontiguousarray(raw)))
        extrinsic = o3d.core.Tensor(np.linalg.inv(T_world_camera), o3d.core.float64, self.device)
        opts = self.options
        # Everything left in ``raw`` is to be integrated: the limit lies one unit above it.
        trunc = opts.depth_trunc_m + 1.0 / depth_scale
        with quiet_open3d(), _open3d_refusal("integrating a depth frame"):
            blocks = self.grid.compute_unique_block_coordinates(
                depth, self.K, extrinsic, depth_scale, trunc,
                trunc_voxel_multiplier=opts.sdf_trunc_voxels,
            )  # fmt: skip
            self.grid.integrate(
                blocks, depth, self.K, extrinsic, depth_scale, trunc,
                trunc_voxel_multiplier=opts.sdf_trunc_voxels,
            )  # fmt: skip
        self.n_frames += 1

    def extract(self) -> tuple[FloatArray, FloatArray]:
        threshold = float(min(self.options.min_observations, self.n_frames))
        with quiet_open3d():
            try:
                cloud = self.grid.extract_point_cloud(weight_threshold=threshold)
            except RuntimeError:
                # Open3D 0.19 fails while attaching colours when no voxel was seen by enough
                # frames (frames that do not overlap): that is an empty surface.
                return np.empty((0, 3)), np.empty((0, 3))
        if "positions" not in cloud.point or len(cloud.point.positions) == 0:
            return np.empty((0, 3)), np.empty((0, 3))
        points = cloud.point.positions.numpy().astype(np.float64)
        normals = cloud.point.normals.numpy().astype(np.float64)
        norms = np.linalg.norm(normals, axis=1, keepdims=True)
        ok = np.isfinite(points).all(axis=1) & np.isfinite(normals).all(axis=1) & (norms[:, 0] > 0)
        points, normals = points[ok], normals[ok] / norms[ok]
        # The hash map hands out blocks in an order that depends on its threads; sorted, the
        # same frames always give the same array (stored artifacts are compared by checksum).
        order = np.lexsort(points.T[::-1])
        return points[order], normals[order]


# --------------------------------------------------------------------------- reader


class RGBDReader(ScanReader):
    """Depth images with intrinsics (and poses): one frame back-projected, several fused."""

    kind: ClassVar[str] = "rgbd"
    options_class: ClassVar[type[ReaderOptions]] = RGBDOptions
    fixed_units: ClassVar[bool] = True
    accepts_folders: ClassVar[bool] = True
    options: RGBDOptions

    def _unit_note(self) -> str:
        return "depth images are converted to metres with their depth_scale"

    def _upload_suffix(self, fmt: str) -> str:
        return ".zip"

    def read(
        self, source: str | Path | bytes, *, fmt: str, units: str = "m", name: str | None = None
    ) -> ScanFile:
        if isinstance(source, bytes):
            if not source:
                raise InputFileError(f"{name or 'upload'} is empty")
            if not source.startswith(b"PK"):
                raise InputFileError(
                    f"{name or 'the upload'} is not a zip archive: an uploaded RGB-D scan must be "
                    "a .zip of the folder (intrinsics.json, depth images, poses or a rgbd.json "
                    "manifest), since a manifest alone cannot carry the images it names"
                )
        return super().read(source, fmt=fmt, units=units, name=name)

    def _read(self, path: Path, *, fmt: str, label: str, scale: float) -> ScanFile:
        with self._frame_set(path, label) as frames:
            return self._read_frames(frames, fmt=fmt)

    @contextlib.contextmanager
    def _frame_set(self, path: Path, label: str) -> Iterator[FrameSet]:
        """The frames of a folder, a zip (unpacked for the duration) or a manifest."""
        if path.is_dir():
            yield load_folder(path, label)
        elif path.name.lower().endswith(".zip") or _is_zip(path):
            with tempfile.TemporaryDirectory(prefix="teachpath-rgbd-") as tmp:
                root = extract_zip(
                    path,
                    Path(tmp),
                    label,
                    max_unpacked_mb=self.options.max_unpacked_mb,
                    limit_source=self.limit_source("max_unpacked_mb"),
                )
                yield load_folder(root, label)
        else:
            yield load_manifest(path, label)

    def _read_frames(self, frames: FrameSet, *, fmt: str) -> ScanFile:
        opts = self.options
        intr = frames.intrinsics
        if opts.depth_scale is not None:
            scale, scale_from = opts.depth_scale, "the options"
        elif frames.depth_scale is not None:
            scale, scale_from = frames.depth_scale, "the manifest"
        elif intr.depth_scale is not None:
            scale, scale_from = intr.depth_scale, "the intrinsics file"
        else:
            scale, scale_from = DEFAULT_DEPTH_SCALE, "the default (millimetres)"
        notes = list(frames.notes)
        notes.append(f"depth_scale {scale:g} raw units per metre, from {scale_from}")
        n = len(frames.frames)
        self._check_pixels(intr, n, frames.layout)
        for frame in frames.frames:
            if frame.color is not None:
                # Named colour must exist and fit; a Scan has no colour channel, so no more.
                info = check_image_file(frame.color, f"colour image {frame.color.name}")
                if info.width is not None and (info.width, info.height) != (
                    intr.width,
                    intr.height,
                ):
                    raise InputFileError(
                        f"colour image {frame.color.name} is {info.width} x {info.height} "
                        f"pixels but the depth is {intr.width} x {intr.height}; register the "
                        "colour to the depth stream when exporting"
                    )
        if n == 1:
            return self._single(frames.frames[0], intr, scale, fmt, notes)
        return self._fused(frames.frames, intr, scale, fmt, notes)

    def _check_pixels(self, intr: Intrinsics, n_frames: int, layout: str) -> None:
        """Refuse more pixels than the options allow, before an image is decoded.

        The intrinsics give every frame's size: each depth PNG's header is checked against them
        before it is decoded (:func:`read_depth`), and colour images are not decoded at all.

        Raises
        ------
        InputTooLargeError
        """
        opts = self.options
        frame = intr.width * intr.height
        if frame > opts.max_frame_pixels:
            setting = self.limit_source("max_frame_pixels")
            raise InputTooLargeError(
                f"{layout}: the depth images are {intr.width} x {intr.height} = {frame:,} pixels "
                f"(by the intrinsics), more than the {opts.max_frame_pixels:,} allowed per image "
                f"({setting}); send the images at the depth camera's own resolution (or scale "
                "them and the intrinsics down)",
                limit="pixels",
                value=opts.max_frame_pixels,
                setting=setting,
            )
        if frame * n_frames > opts.max_pixels:
            setting = self.limit_source("max_pixels")
            raise InputTooLargeError(
                f"{layout}: the {n_frames} depth images of {intr.width} x {intr.height} hold "
                f"{frame * n_frames:,} pixels, more than the {opts.max_pixels:,} allowed in all "
                f"({setting}); send at most {opts.max_pixels // frame} frames (every second or "
                "third frame of a slow sweep fuses as well)",
                limit="pixels",
                value=opts.max_pixels,
                setting=setting,
            )

    def _single(
        self, frame: Frame, intr: Intrinsics, scale: float, fmt: str, notes: list[str]
    ) -> ScanFile:
        opts = self.options
        raw = read_depth(frame.depth, intr, frame.name)
        median = depth_median_m(raw, scale)
        if median is None:
            raise InputFileError(
                f"{frame.name} holds no depth measurement (every pixel is 0); capture again"
            )
        check_depth_scale(median, scale, opts.depth_trunc_m, frame.name)
        raw, dropped = truncate_depth(raw, depth_scale=scale, depth_trunc_m=opts.depth_trunc_m)
        points = backproject(raw, intr, depth_scale=scale, T_world_camera=frame.T_world_camera)
        if dropped:
            notes.append(f"{dropped} depths beyond depth_trunc_m {opts.depth_trunc_m:g} m left out")
        if frame.T_world_camera is None:
            notes.append("one frame without a pose: the scan is in the camera frame")
        if not len(points):
            raise InputFileError(f"{frame.name} has no depth within {opts.depth_trunc_m:g} m")
        return ScanFile(
            Scan(points_m=points),
            format=fmt,
            n_dropped=dropped,
            notes=tuple(notes),
            dropped_because=DROPPED_DEPTH,
        )

    def _fused(
        self, frames: tuple[Frame, ...], intr: Intrinsics, scale: float, fmt: str, notes: list[str]
    ) -> ScanFile:
        opts = self.options
        posed = [(f, f.T_world_camera) for f in frames if f.T_world_camera is not None]
        missing = [f.name for f in frames if f.T_world_camera is None]
        if missing:
            raise InputFileError(
                f"no camera pose for frame {missing[0]}"
                + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else "")
                + "; fusing several frames needs T_world_camera for every one"
            )
        tsdf = _TSDF(intr, opts) if opts.fusion == "tsdf" else None
        clouds: list[FloatArray] = []
        empty: list[str] = []
        checked = False
        n_dropped = 0
        for frame, T_world_camera in posed:
            raw = read_depth(frame.depth, intr, frame.name)
            median = depth_median_m(raw, scale)
            if median is None:
                empty.append(frame.name)
                continue
            if not checked:
                # One frame suffices: a wrong scale is wrong for all of them.
                check_depth_scale(median, scale, opts.depth_trunc_m, frame.name)
                checked = True
            raw, dropped = truncate_depth(raw, depth_scale=scale, depth_trunc_m=opts.depth_trunc_m)
            n_dropped += dropped
            if tsdf is not None:
                tsdf.integrate(raw, scale, T_world_camera)
            else:
                clouds.append(
                    backproject(raw, intr, depth_scale=scale, T_world_camera=T_world_camera)
                )
        used = len(frames) - len(empty)
        if not used:
            raise InputFileError(
                f"none of the {len(frames)} depth images holds a measurement (all pixels are 0)"
            )
        if empty:
            notes.append(
                f"{len(empty)} frame(s) without any depth skipped ({', '.join(empty[:3])}"
                + (", ..." if len(empty) > 3 else "")
                + ")"
            )
        if n_dropped:
            notes.append(
                f"{n_dropped} depths beyond depth_trunc_m {opts.depth_trunc_m:g} m left out"
            )
        if tsdf is not None:
            points, normals = tsdf.extract()
            notes.append(
                f"fused {used} frames with a TSDF ({opts.voxel_m * 1e3:g} mm voxels, seen by at "
                f"least {min(opts.min_observations, used)} frame(s))"
            )
        else:
            cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.concatenate(clouds)))
            points = np.asarray(cloud.voxel_down_sample(opts.voxel_m).points, dtype=np.float64)
            normals = None
            notes.append(f"merged {used} frames, averaged in {opts.voxel_m * 1e3:g} mm voxels")
        if not len(points):
            raise InputFileError(
                f"fusing {used} frames gave no surface: the poses may not be T_world_camera "
                "(camera to world) or the frames do not overlap; check the pose file"
            )
        return ScanFile(
            Scan(points_m=points, normals=normals),
            format=fmt,
            n_dropped=n_dropped,
            dropped_because=DROPPED_DEPTH,
            notes=tuple(notes),
        )


def _is_zip(path: Path) -> bool:
    with path.open("rb") as handle:
        return handle.read(4) == b"PK\x03\x04"
