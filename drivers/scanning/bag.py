"""Intel RealSense recordings (``.bag``), read with Open3D's ``o3d.t.io.RSBagReader``.

A bag is a ROS1 bag that librealsense plays back without a camera. Open3D's reader needs one
depth stream (Z16) and one colour stream (RGB8/BGR8) at the same frame rate, and hands out the
depth aligned to the colour camera, whose intrinsics the metadata gives. A bag holds no camera
poses, so the reader assumes a camera that stood still (on a tripod or the robot) while
recording: it takes ``n_frames`` frames after skipping ``first_frame`` and keeps, per pixel, the
median of the frames that measured it, which removes most of the frame-to-frame noise. A bag of
a moving camera needs its poses: export its frames with Open3D's reconstruction system and read
the folder as RGB-D frames.

librealsense decodes the bag on a thread of its own, and an error there terminates the process
(Open3D raises from that thread). The bag is therefore decoded in a child process under a time
and memory limit (:func:`drivers.isolation.run_isolated` runs :func:`decode_bag`), so a corrupt
recording costs an error message, not the service's worker.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field

from drivers.errors import InputFileError, ReaderCrashError, ResourceLimitError
from drivers.isolation import Limits, run_isolated
from drivers.scanning.base import DROPPED_DEPTH, ReaderOptions, ScanFile, ScanReader
from drivers.scanning.rgbd import (
    DEFAULT_DEPTH_SCALE,
    Intrinsics,
    backproject,
    check_depth_scale,
    depth_median_m,
    truncate_depth,
)
from recon.inputs import Scan

#: A ROS1 bag (what librealsense records) starts with this line.
BAG_SIGNATURE = b"#ROSBAG V2.0\n"

# What went wrong in the child (BagReadError.status).
_EXIT_CANNOT_OPEN = 3
_EXIT_NO_FRAMES = 4
_EXIT_BAD_STREAMS = 5

#: Address space allowed to the child: the interpreter with Open3D and librealsense (about
#: 0.5 GB mapped), plus the frames it keeps (a 1280 x 720 Z16 frame is 1.8 MB; kept once in the
#: list and once stacked, with room for the colour frame being decoded).
CHILD_MEMORY_BYTES = 2 << 30
CHILD_MEMORY_PER_FRAME_BYTES = 16 << 20
#: What the child runs, "module:function".
_CHILD_TARGET = "drivers.scanning.bag:decode_bag"


class BagOptions(ReaderOptions):
    """Options of the RealSense bag reader.

    Attributes
    ----------
    first_frame : int
        Frames skipped at the start (auto-exposure settles during the first few).
    n_frames : int
        Frames combined by a per-pixel median (static camera).
    min_valid_fraction : float
        A pixel is kept if at least this fraction of the frames measured it: pixels that flicker
        in and out are usually flying pixels at edges.
    depth_scale : float or None
        Raw depth units per metre; None: from the bag (librealsense's depth units), else 1000.
    depth_trunc_m : float
        Depths beyond this are left out (and counted).
    timeout_s : float
        How long the child process may take to decode the bag.
    """

    kind: Literal["bag"] = "bag"
    first_frame: int = Field(0, ge=0)
    n_frames: int = Field(15, ge=1, le=1000)
    min_valid_fraction: float = Field(0.5, gt=0, le=1)
    depth_scale: float | None = Field(None, gt=0)
    depth_trunc_m: float = Field(3.0, gt=0)
    timeout_s: float = Field(300.0, gt=0)


class RealSenseBagReader(ScanReader):
    """A RealSense ``.bag`` of a static camera: the median of a few frames, back-projected."""

    kind: ClassVar[str] = "bag"
    options_class: ClassVar[type[ReaderOptions]] = BagOptions
    fixed_units: ClassVar[bool] = True
    options: BagOptions

    def _unit_note(self) -> str:
        return "the bag's depth units convert depth to metres"

    def _read(self, path: Path, *, fmt: str, label: str, scale: float) -> ScanFile:
        with path.open("rb") as handle:
            head = handle.read(len(BAG_SIGNATURE))
        if not head:
            raise InputFileError(f"{label} is empty")
        if head != BAG_SIGNATURE:
            raise InputFileError(
                f"{label} is not a RealSense recording (a ROS bag starts with "
                f"{BAG_SIGNATURE.strip().decode()!r}); record it with the RealSense Viewer or "
                "rs-record"
            )
        frames = self._extract_in_child(path, label)
        return frames_to_scan(frames, self.options, label=label, fmt=fmt)

    def _extract_in_child(self, path: Path, label: str) -> dict[str, Any]:
        opts = self.options
        memory_bytes = CHILD_MEMORY_BYTES + CHILD_MEMORY_PER_FRAME_BYTES * opts.n_frames
        limits = Limits(
            time_s=opts.timeout_s,
            memory_bytes=memory_bytes,
            time_setting="timeout_s",
            memory_setting="n_frames",
        )
        try:
            return run_isolated(
                _CHILD_TARGET,
                (str(path), opts.first_frame, opts.n_frames, label),
                limits=limits,
                what=f"reading {label}",
            )
        except ResourceLimitError as exc:
            if exc.limit == "time":
                message = (
                    f"reading {label} took longer than {opts.timeout_s:g} s; read fewer frames "
                    "(n_frames) or raise timeout_s"
                )
            else:
                # The limit in force: lower than asked when this runs under a parse's own.
                limit_bytes = exc.value or memory_bytes
                message = (
                    f"reading {label} needed more than {limit_bytes / 2**20:.0f} MB of "
                    f"memory for {opts.n_frames} frames; read fewer frames (n_frames)"
                )
            raise ResourceLimitError(
                message, limit=exc.limit, value=exc.value, setting=exc.setting
            ) from None
        except ReaderCrashError as exc:
            how = exc.signal_name or f"exit status {exc.exit_code}"
            raise ReaderCrashError(
                f"the RealSense library crashed reading {label} ({how}); the recording is "
                "likely truncated or corrupt: record it again",
                signal_name=exc.signal_name,
                exit_code=exc.exit_code,
                output_tail=exc.output_tail,
            ) from None


def median_depth(stack: np.ndarray, min_valid_fraction: float) -> np.ndarray:
    """Per-pixel median of the frames that measured a pixel.

    Parameters
    ----------
    stack : ndarray of shape (F, H, W), uint16
        Raw depth frames, 0 = no measurement.
    min_valid_fraction : float
        Pixels measured in fewer than this fraction of the frames become 0.

    Returns
    -------
    ndarray of shape (H, W), uint16
    """
    valid = stack > 0
    count = valid.sum(axis=0)
    values = np.where(valid, stack.astype(np.float32), np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN pixels: dropped by ``keep``
        median = np.nanmedian(values, axis=0)
    keep = (count >= np.ceil(min_valid_fraction * len(stack))) & (count > 0)
    return np.where(keep, np.rint(median), 0).astype(np.uint16)


def frames_to_scan(
    frames: dict[str, Any], options: BagOptions, *, label: str, fmt: str = "bag"
) -> ScanFile:
    """A scan from decoded bag frames (what the child process returns).

    Parameters
    ----------
    frames : dict
        ``depth``: ndarray of shape (F, H, W), uint16; ``K``: ndarray (3, 3) of the colour
        camera the depth is aligned to; ``size``: (width, height); ``depth_scale``: raw units
        per metre from the bag (0 if unknown).
    options : BagOptions
    label : str
        The bag's name, for messages.

    Raises
    ------
    InputFileError
        No depth at all, or a depth scale that puts the scene out of range.
    """
    stack = np.asarray(frames["depth"])
    K = np.asarray(frames["K"], dtype=np.float64)
    width, height = (int(v) for v in np.asarray(frames["size"]))
    if stack.ndim != 3 or stack.shape[1:] != (height, width):
        raise InputFileError(
            f"{label}: depth frames of shape {stack.shape[1:]} do not match the colour "
            f"camera's {height} x {width} they should be aligned to"
        )
    intrinsics = Intrinsics(width, height, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    notes = []
    bag_scale = float(frames.get("depth_scale", 0.0))
    if options.depth_scale is not None:
        scale, scale_from = options.depth_scale, "the options"
    elif np.isfinite(bag_scale) and bag_scale > 0:
        scale, scale_from = bag_scale, "the bag"
    else:
        scale, scale_from = DEFAULT_DEPTH_SCALE, "the default (millimetres; the bag gave none)"
    notes.append(f"depth_scale {scale:g} raw units per metre, from {scale_from}")
    raw = median_depth(stack, options.min_valid_fraction)
    notes.append(
        f"per-pixel median of {len(stack)} frame(s) after skipping {options.first_frame} "
        "(static camera assumed)"
    )
    median = depth_median_m(raw, scale)
    if median is None:
        raise InputFileError(
            f"{label}: no pixel has depth in at least {options.min_valid_fraction:.0%} of the "
            f"{len(stack)} frames read; check the recording or lower min_valid_fraction"
        )
    check_depth_scale(median, scale, options.depth_trunc_m, label)
    raw, dropped = truncate_depth(raw, depth_scale=scale, depth_trunc_m=options.depth_trunc_m)
    points = backproject(raw, intrinsics, depth_scale=scale)
    if dropped:
        notes.append(f"{dropped} depths beyond depth_trunc_m {options.depth_trunc_m:g} m left out")
    if not len(points):
        raise InputFileError(f"{label} has no depth within {options.depth_trunc_m:g} m")
    return ScanFile(
        Scan(points_m=points),
        format=fmt,
        n_dropped=dropped,
        notes=tuple(notes),
        dropped_because=DROPPED_DEPTH,
    )


class BagReadError(Exception):
    """A failure in the child process, with the exit status that tells the parent what it was."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


def extract_frames(
    path: str,
    first_frame: int,
    n_frames: int,
    *,
    reader_factory: Callable[[], Any] | None = None,
) -> dict[str, Any]:
    """Decode up to ``n_frames`` depth frames after ``first_frame`` with Open3D's RSBagReader.

    Runs in the child process (see the module docstring); ``reader_factory`` lets tests stand in
    for the reader. Returns the dict :func:`frames_to_scan` takes.

    Raises
    ------
    BagReadError
    """
    import open3d as o3d

    from drivers.scanning._native import quiet_open3d

    factory = reader_factory or o3d.t.io.RSBagReader
    reader = factory()
    with quiet_open3d():
        try:
            opened = reader.open(path)
        except RuntimeError as exc:  # Open3D raises when the streams are not what it reads
            raise BagReadError(_EXIT_CANNOT_OPEN, str(exc)) from None
    if not opened:
        raise BagReadError(_EXIT_CANNOT_OPEN, "Open3D's RSBagReader.open() returned False")
    try:
        metadata = reader.metadata
        intrinsic = metadata.intrinsics
        K = np.asarray(intrinsic.intrinsic_matrix, dtype=np.float64)
        size = np.array([intrinsic.width, intrinsic.height])
        if size.min() <= 0:
            raise BagReadError(_EXIT_BAD_STREAMS, "the colour stream reports no image size")
        depth_frames: list[np.ndarray] = []
        index = 0
        with quiet_open3d():
            while len(depth_frames) < n_frames and not reader.is_eof():
                rgbd = reader.next_frame()
                if rgbd.is_empty():
                    break  # end of the recording
                if index >= first_frame:
                    depth = rgbd.depth.as_tensor().numpy()
                    if depth.ndim == 3:
                        depth = depth[..., 0]
                    if depth.dtype != np.uint16:
                        raise BagReadError(
                            _EXIT_BAD_STREAMS, f"depth frames are {depth.dtype}, not Z16 (uint16)"
                        )
                    depth_frames.append(np.array(depth))
                index += 1
    finally:
        reader.close()
    if not depth_frames:
        raise BagReadError(_EXIT_NO_FRAMES, "no frames")
    return {
        "depth": np.stack(depth_frames),
        "K": K,
        "size": size,
        "depth_scale": np.float64(getattr(metadata, "depth_scale", 0.0) or 0.0),
    }


def decode_bag(path: str, first_frame: int, n_frames: int, label: str) -> dict[str, Any]:
    """:func:`extract_frames` with its failures as the messages a user reads.

    Runs in the child process (see the module docstring).

    Raises
    ------
    InputFileError
        The bag cannot be played, holds no frames after ``first_frame``, or has unusable
        streams.
    """
    try:
        return extract_frames(path, first_frame, n_frames)
    except BagReadError as exc:
        detail = str(exc)
        if exc.status == _EXIT_CANNOT_OPEN:
            raise InputFileError(
                f"librealsense cannot play {label}: it is truncated or corrupt, or lacks a "
                "depth (Z16) and a colour (RGB8/BGR8) stream at the same frame rate, which "
                "Open3D's reader needs" + (f" ({detail})" if detail else "")
            ) from None
        if exc.status == _EXIT_NO_FRAMES:
            raise InputFileError(
                f"{label} holds no frames after the first {first_frame} skipped; "
                "record longer or lower first_frame"
            ) from None
        raise InputFileError(f"{label} has unusable streams: {detail}") from None
