"""C3D marker files (Motive's, Vicon's and most biomechanics tools' binary export), via ezc3d.

One marker is the trace: the pen-tip marker, named in the file's ``POINT:LABELS``. Positions are
in ``POINT:UNITS``; a sample whose residual is negative is invalid (the marker was not seen).

ezc3d is a C++ library, and some damaged files make it crash the whole process (a segmentation
fault) or loop forever -- found by feeding it mutated files. So the file is parsed in a short-lived
child process with a time and memory limit (:func:`drivers.isolation.run_isolated`), and a crash
there becomes an :class:`InputFileError` here (about 0.2 s of start-up per file, measured).

Two things the reader checks that ezc3d does not say:

* A truncated file: ezc3d returns the frames it could read and adjusts its frame count to match,
  so the count is compared with the file's own header and with the bytes present.
* A header whose last-frame word disagrees with ``POINT:FRAMES``: the count that the data
  section holds exactly is trusted, so such a file is read and a truncated one still refused.
* A file that declares more frames than it holds but ends exactly after a complete frame, off a
  512-byte block (NDI's Optotrak software: frames 1-1149 declared, 29 held, no padding): the
  frames held are read and the reader's notes say so. A copy cut mid-frame or on a block is
  refused as truncated.
* Takes over 65535 frames: the header's frame numbers are 16-bit, so long files declare their
  length in ``POINT:LONG_FRAMES`` or ``TRIAL:ACTUAL_START_FIELD`` / ``ACTUAL_END_FIELD``. ezc3d
  1.7 stops at frame 65535 regardless; the remaining frames of a float-format (Intel) file are
  read here, after checking that the first 65535 agree exactly with ezc3d's.
"""

from __future__ import annotations

import struct
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from drivers.errors import InputFileError, ReaderCrashError, ResourceLimitError
from drivers.isolation import Limits, run_isolated
from drivers.tracking.base import SampleBatch, name_excerpt
from drivers.units import metres_per
from recon.arrays import FloatArray
from recon.inputs import Recording

#: Metres per unit, by the (lower-case) names found in ``POINT:UNITS``.
C3D_LENGTH_UNITS: dict[str, float] = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}
#: Time allowed to the child process: a base plus a rate. ezc3d reads about 50 MB/s here; the
#: margin is for a loaded machine, not for slow files.
CHILD_TIMEOUT_S = 30.0
CHILD_TIMEOUT_S_PER_MB = 2.0
#: Address space allowed to the child: ezc3d keeps each point of each frame as an object of about
#: 250 bytes, some 16 times the file's size, on top of the interpreter and numpy.
CHILD_MEMORY_BYTES = 1 << 30
CHILD_MEMORY_PER_FILE_BYTE = 40
#: What the child runs, "module:function" (tests replace it to simulate a crash or a hang).
_CHILD_TARGET = "drivers.tracking.c3d:parse_with_ezc3d"
#: Frames ezc3d 1.7 reads at most (the header's 16-bit limit).
_EZC3D_MAX_FRAMES = 0xFFFF
_INTEL = 84


@dataclass(frozen=True)
class C3DTrace:
    """One marker of a C3D file.

    Attributes
    ----------
    batch : SampleBatch
        ``t_s`` (N,) seconds, frame number over ``POINT:RATE``; ``position_m`` (N, 3) metres, NaN
        where the marker was not seen; ``orientation_xyzw`` None; ``valid`` (N,) False where not
        seen.
    rate_hz : float
        ``POINT:RATE``.
    units : str
        ``POINT:UNITS`` as written ("mm"…), or the unit passed if the file has none.
    marker : str
        The marker read.
    available : tuple of str
        The marker labels in the file.
    residual_m : ndarray of shape (N,), metres
        The tracker's residual per sample (0 for interpolated samples); NaN where not seen.
    first_frame : int
        Number of the first frame (0-based), which ``t_s`` counts from.
    notes : tuple of str
        What the reader reconciled (a header that disagrees with the data it holds).
    """

    batch: SampleBatch
    rate_hz: float
    units: str
    marker: str
    available: tuple[str, ...]
    residual_m: FloatArray
    first_frame: int = 0
    notes: tuple[str, ...] = ()

    def __len__(self) -> int:
        return len(self.batch)

    def to_recording(self) -> Recording:
        """The valid samples as a :class:`~recon.inputs.Recording` (lost frames left out).

        Raises
        ------
        InputFileError
            Fewer than two valid samples.
        """
        keep = self.batch.valid
        if int(keep.sum()) < 2:
            raise InputFileError(
                f"marker {self.marker!r} is seen in {int(keep.sum())} of {len(keep)} frames; a "
                "trace needs at least two"
            )
        return Recording(points_m=self.batch.position_m[keep], t_s=self.batch.times_s()[keep])


def read_c3d(
    source: str | Path | bytes,
    *,
    marker: str | None = None,
    units: str | None = None,
    name: str | None = None,
) -> C3DTrace:
    """Read one marker's trajectory from a C3D file.

    Parameters
    ----------
    source : path or bytes
        The file, or its content (an upload).
    marker : str, optional
        The marker label; needed when the file has several markers.
    units : {"m", "mm"}, optional
        Length unit of the positions, used only when the file has no ``POINT:UNITS``.
    name : str, optional
        The file's name, for messages (uploads).

    Returns
    -------
    C3DTrace

    Raises
    ------
    InputFileError
        Missing, empty, truncated or damaged file, not a C3D file, no marker of that name (or
        several and none named), no length unit, no frame rate.
    ValueError
        An unknown ``units`` or an empty ``marker``.
    """
    if marker is not None and not marker.strip():
        raise ValueError("marker must be a marker label, not an empty string")
    fallback_scale = None if units is None else metres_per(units)
    name = name or ("upload" if isinstance(source, bytes) else str(source))
    with tempfile.TemporaryDirectory(prefix="teachpath-c3d-") as tmp:
        if isinstance(source, bytes):
            path = Path(tmp) / "upload.c3d"
            path.write_bytes(source)
        else:
            path = Path(source)
            if not path.exists():
                raise InputFileError(f"{name} does not exist")
            if path.is_dir():
                raise InputFileError(f"{name} is a directory, not a C3D file")
        try:
            size = path.stat().st_size
            with path.open("rb") as handle:
                # The header and, at most 254 blocks on, the parameter section's first bytes.
                head = handle.read(512 * 256)
        except OSError as exc:
            raise InputFileError(f"cannot read {name}: {exc.strerror}") from None
        if size == 0:
            raise InputFileError(f"{name} is empty; expected a C3D file")
        if size < 1024 or (head[0] != 0 and head[1] != 0x50):
            raise InputFileError(
                f"{name} is not a C3D file (it lacks the C3D header and parameter blocks); "
                "export the take as C3D again, or as CSV"
            )
        parsed = _parse_in_child(path, marker, size, name)
        notes: list[str] = []
        labels = tuple(str(label) for label in parsed["labels"])
        if "points" not in parsed:
            raise _no_marker(name, marker, labels)
        chosen = labels[int(parsed["index"])]
        points = parsed["points"]
        residuals = parsed["residuals"]
        points, residuals = _check_frame_count(
            path, head, size, parsed, points, residuals, name, notes
        )

    rate = float(parsed["rate"])
    if not (np.isfinite(rate) and rate > 0):
        raise InputFileError(f"{name} has no frame rate (POINT:RATE is {rate}); export it again")
    declared = str(parsed["units"]).strip()
    if declared:
        scale = C3D_LENGTH_UNITS.get(declared.lower())
        if scale is None:
            raise InputFileError(
                f"{name} has an unknown length unit {declared!r} in POINT:UNITS; export it in "
                "mm or m"
            )
    elif fallback_scale is None:
        raise InputFileError(
            f"{name} does not say its length unit (POINT:UNITS is empty); pass the unit the "
            "positions are in (units='mm' or 'm')"
        )
    else:
        scale, declared = fallback_scale, str(units)

    seen = np.isfinite(points).all(axis=1) & ~(residuals < 0) & np.isfinite(residuals)
    position = np.where(seen[:, None], points * scale, np.nan)
    first = int(parsed["first_frame"])
    t = (first + np.arange(len(position))) / rate
    return C3DTrace(
        batch=SampleBatch(t_s=t, position_m=position, orientation_xyzw=None, valid=seen),
        rate_hz=rate,
        units=declared,
        marker=chosen,
        available=labels,
        residual_m=np.where(seen, residuals * scale, np.nan),
        first_frame=first,
        notes=tuple(notes),
    )


def _no_marker(name: str, marker: str | None, labels: tuple[str, ...]) -> InputFileError:
    listed = name_excerpt(labels)
    if not labels:
        return InputFileError(f"{name} has no markers (POINT:LABELS is empty)")
    if marker is None:
        return InputFileError(
            f"{name} has {len(labels)} markers ({listed}); say which one is the pen tip "
            "(marker=...)"
        )
    return InputFileError(f"{name} has no marker named {marker!r}; it has {listed}")


def _parse_in_child(path: Path, marker: str | None, size: int, name: str) -> dict[str, np.ndarray]:
    """Run ezc3d on ``path`` in a child process; its arrays, or an InputFileError."""
    memory_bytes = CHILD_MEMORY_BYTES + CHILD_MEMORY_PER_FILE_BYTE * size
    limits = Limits(
        time_s=CHILD_TIMEOUT_S + CHILD_TIMEOUT_S_PER_MB * size / 1e6,
        memory_bytes=memory_bytes,
    )
    try:
        return run_isolated(
            _CHILD_TARGET, (str(path), marker, name), limits=limits, what="the C3D reader"
        )
    except ResourceLimitError as exc:
        # Limits scaled to the file's size are only reached by a damaged file.
        spent = (
            f"did not finish within {limits.time_s:.0f} s"
            if exc.limit == "time"
            else f"needed more than {memory_bytes / 2**20:.0f} MB of memory"
        )
        raise ResourceLimitError(
            f"{name} could not be read: the C3D reader {spent}, which a damaged file causes; "
            "export the take again",
            limit=exc.limit,
            value=exc.value,
            setting=exc.setting,
        ) from None
    except ReaderCrashError as exc:
        if exc.signal_name is not None:
            message = f"{name} is damaged: it made the C3D reader crash ({exc.signal_name})"
        else:
            message = (
                f"{name} could not be read: the C3D reader exited (status {exc.exit_code}) "
                "without an answer"
            )
        raise ReaderCrashError(
            f"{message}; export the take again",
            signal_name=exc.signal_name,
            exit_code=exc.exit_code,
            output_tail=exc.output_tail,
        ) from None


def parse_with_ezc3d(source: str, marker: str | None, name: str) -> dict[str, np.ndarray]:
    """Parse a C3D file with ezc3d: what :func:`read_c3d` needs of it, as arrays.

    Runs in a child process (see the module docstring): ezc3d may crash or hang on a damaged
    file.

    Parameters
    ----------
    source : str
        The file.
    marker : str or None
        The marker whose samples to return.
    name : str
        The file's name for messages.

    Returns
    -------
    dict of str to ndarray
        ``labels``, ``units``, ``rate``, ``first_frame``, ``long_frames``, and if present
        ``trial_frames``; with the marker found, its ``index``, ``points`` (N, 3) and
        ``residuals`` (N,).

    Raises
    ------
    InputFileError
        ezc3d refused the file (its reason in the message).
    """
    import ezc3d  # not installed: an ImportError, which the isolation reports as such

    try:
        c3d = ezc3d.c3d(source)
        point = c3d["parameters"]["POINT"]
        labels = [str(label).strip() for label in point["LABELS"]["value"]]
        i = 2
        while f"LABELS{i}" in point:  # more than 255 markers continue in LABELS2, LABELS3...
            labels += [str(label).strip() for label in point[f"LABELS{i}"]["value"]]
            i += 1
        units = point["UNITS"]["value"]
        rate = point["RATE"]["value"]
        arrays: dict[str, np.ndarray] = {
            "labels": np.array(labels, dtype=str),
            "units": np.array(str(units[0]) if len(units) else ""),
            "rate": np.array(float(rate[0]) if len(rate) else np.nan),
            "first_frame": np.array(int(c3d["header"]["points"]["first_frame"])),
            "long_frames": np.array(_first_number(point, "LONG_FRAMES")),
        }
        trial = c3d["parameters"].get("TRIAL", {})
        words = [
            trial.get(key, {}).get("value", [])
            for key in ("ACTUAL_START_FIELD", "ACTUAL_END_FIELD")
        ]
        if all(len(w) == 2 for w in words):
            # Two 16-bit words each (low, high), stored in signed INT parameters.
            start, end = ((int(w[0]) & 0xFFFF) | ((int(w[1]) & 0xFFFF) << 16) for w in words)
            arrays["trial_frames"] = np.array(end - start + 1)
        index = None
        if marker is not None and marker in labels:
            index = labels.index(marker)
        elif marker is None and len(labels) == 1:
            index = 0
        if index is not None:
            arrays["index"] = np.array(index)
            arrays["points"] = np.ascontiguousarray(c3d["data"]["points"][:3, index, :].T)
            residuals = c3d["data"]["meta_points"]["residuals"]
            arrays["residuals"] = np.ascontiguousarray(residuals[0, index, :])
    except MemoryError:
        raise  # the isolation reports the memory limit
    except Exception as exc:  # noqa: BLE001 - any failure of the parser is the file's
        message = " ".join(str(exc).split()) or type(exc).__name__
        # ezc3d's advice is about its own API, and its stream suffix says nothing to a user.
        message = message.split(" If you want to ignore")[0].replace(": iostream error", "")
        raise InputFileError(
            f"{name} is not a readable C3D file ({message}); export the take again, as C3D or CSV"
        ) from None
    return arrays


def _first_number(group: dict[str, Any], key: str) -> float:
    values = group.get(key, {}).get("value", [])
    return float(values[0]) if len(values) else -1.0


def _check_frame_count(
    path: Path,
    head: bytes,
    size: int,
    parsed: dict[str, np.ndarray],
    points: np.ndarray,
    residuals: np.ndarray,
    name: str,
    notes: list[str] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The marker's samples after checking that ezc3d read every frame the file holds
    (``notes`` receives what was reconciled on the way)."""
    notes = [] if notes is None else notes
    n_read = len(points)
    layout = _raw_layout(head)
    if layout is None:
        return points, residuals  # leading zero bytes (a Vicon quirk): trust ezc3d
    long_frames = float(parsed["long_frames"])
    available = layout.frames_in(size)
    # The data section ends on a 512-byte block: the padding may look like a few frames.
    padding = 511 // (layout.frame_bytes or 1)
    declared = None
    if long_frames > 0:
        declared = int(round(long_frames))
    elif "trial_frames" in parsed and int(parsed["trial_frames"]) > 0:
        declared = int(parsed["trial_frames"])
    elif layout.last_frame != 0xFFFF:
        declared = _header_or_parameter(
            layout.header_frames,
            _raw_point_frames(head),
            n_read if available is None else available,
            0 if available is None else padding,
            name,
        )
    if declared is None:
        if n_read >= _EZC3D_MAX_FRAMES and available is not None and available > n_read + padding:
            raise InputFileError(
                f"{name} holds more than {_EZC3D_MAX_FRAMES} frames but does not say how many "
                "(no POINT:LONG_FRAMES or TRIAL:ACTUAL_END_FIELD); export a shorter take or "
                "use the CSV export"
            )
        return points, residuals
    ends_on_a_frame = (
        available is not None
        and layout.frame_bytes is not None
        and size % 512 != 0
        and size == (layout.data_start - 1) * 512 + available * layout.frame_bytes
    )
    if available is not None and 0 < available < declared and ends_on_a_frame:
        # The file ends exactly after its last complete frame, and not on a 512-byte block: an
        # export of fewer frames than it declares (NDI's Optotrak software writes frames
        # 1-1149 in the header and in POINT:FRAMES of a 29-frame file, unpadded), not a copy
        # cut short (which ends mid-frame, or on a block as buffered copies do). Read what it
        # holds and say so; a cut that happens to fall exactly on a frame is read the same way,
        # and the note says what to do then.
        notes.append(
            f"the header says {declared} frames; the file holds {available} complete frames "
            f"and ends there: the {available} were read (if the take was longer, the file was "
            "cut: export it again)"
        )
        declared = available
    if available is not None and available < declared:
        raise InputFileError(
            f"{name} is truncated: it declares {declared} frames but holds {available}; copy or "
            "export the take again"
        )
    if n_read >= declared:
        return points, residuals
    if n_read < _EZC3D_MAX_FRAMES:
        raise InputFileError(
            f"{name} is truncated or damaged: it declares {declared} frames but only {n_read} "
            "could be read; copy or export the take again"
        )
    return _read_long_take(path, layout, parsed, points, residuals, declared, name)


def _raw_point_frames(head: bytes) -> int:
    """``POINT:FRAMES`` as the file's parameter section has it, or -1 if it cannot be found.

    Read here rather than taken from ezc3d, which rewrites it to the frames it could read.
    """
    start = (head[0] - 1) * 512 if head else -1
    if start < 0 or start + 4 > len(head) or head[start + 3] not in (84, 85, 86):
        return -1
    processor = head[start + 3]
    order = ">" if processor == 86 else "<"  # MIPS is big-endian; Intel and DEC little
    groups: dict[int, str] = {}
    frames = []
    pos = start + 4
    # Entries: name length and group id (signed bytes; a negative id is a group's own entry),
    # the name, then the offset of the next entry from this word, then a parameter's contents.
    while pos + 2 <= len(head):
        size, group = struct.unpack("bb", head[pos : pos + 2])
        end = pos + 2 + abs(size)
        if size == 0 or end + 2 > len(head):
            break
        label = head[pos + 2 : end].decode("ascii", errors="replace").strip().upper()
        (offset,) = struct.unpack(order + "h", head[end : end + 2])
        if group < 0:
            groups[-group] = label
        elif label == "FRAMES":
            frames.append((group, end + 2))
        if offset <= 0:
            break
        pos = end + offset
    for group, at in frames:
        if groups.get(group) == "POINT":
            return _first_int(head, at, processor)
    return -1


def _first_int(head: bytes, at: int, processor: int) -> int:
    """The first value of the parameter whose type byte is at ``at``: an INT or an IEEE REAL."""
    if at + 2 > len(head):
        return -1
    order = ">" if processor == 86 else "<"
    kind, dims = struct.unpack("bB", head[at : at + 2])
    value_at = at + 2 + dims
    if kind == 2 and value_at + 2 <= len(head):
        # A signed 16-bit INT: 32768-65535 frames are written as negative numbers.
        frames: int = struct.unpack(order + "h", head[value_at : value_at + 2])[0] & 0xFFFF
        return frames
    if kind == 4 and processor != 85 and value_at + 4 <= len(head):
        return int(round(struct.unpack(order + "f", head[value_at : value_at + 4])[0]))
    return -1  # DEC floats, bytes, text: not read here


def _header_or_parameter(
    header_frames: int, point_frames: int, held: int, padding: int, name: str
) -> int:
    """The frame count to check the data against, when the header and ``POINT:FRAMES`` disagree.

    Some writers (NDI's Optotrak software) put the take's frame range in the header and the
    exported frames in ``POINT:FRAMES``; whichever the data section holds exactly is the file's.
    ``held`` is the frames the bytes hold, up to ``padding`` more from the last block's filler.
    """
    if point_frames <= 0 or point_frames == header_frames:
        return header_frames
    for count in (point_frames, header_frames):
        if count <= held <= count + padding:
            return count
    if held < min(point_frames, header_frames):
        raise InputFileError(
            f"{name} is truncated: it declares {point_frames} frames (POINT:FRAMES; its header "
            f"says {header_frames}) but holds {held}; copy or export the take again"
        )
    return header_frames  # neither fits: checked against the header, as before


@dataclass(frozen=True)
class _Layout:
    """What the 512-byte header says about the data section."""

    processor: int
    n_points: int
    analog_per_frame: int
    first_frame: int
    last_frame: int
    scale: float | None  # None for DEC and MIPS floats (only their sign would be read)
    data_start: int

    @property
    def header_frames(self) -> int:
        # ezc3d's reading of first/last: 1-based unless the first frame is written as 0.
        return self.last_frame - self.first_frame + 1 if self.first_frame else self.last_frame + 1

    @property
    def frame_bytes(self) -> int | None:
        if self.scale is None:
            return None
        word = 4 if self.scale < 0 else 2  # float data, or integers times the scale
        return word * (4 * self.n_points + self.analog_per_frame)

    def frames_in(self, size: int) -> int | None:
        frame = self.frame_bytes
        if not frame or self.data_start < 2:
            return None
        return max(size - (self.data_start - 1) * 512, 0) // frame


def _raw_layout(head: bytes) -> _Layout | None:
    if len(head) < 512 or head[1] != 0x50 or head[0] < 2:
        return None
    processor_at = (head[0] - 1) * 512 + 3
    if processor_at >= len(head):
        return None
    processor = head[processor_at]
    order = ">" if processor == 86 else "<"  # MIPS is big-endian; Intel and DEC little
    n_points, analog, first, last = struct.unpack(order + "4H", head[2:10])
    (data_start,) = struct.unpack(order + "H", head[16:18])
    scale = struct.unpack("<f", head[12:16])[0] if processor == _INTEL else None
    return _Layout(processor, n_points, analog, first, last, scale, data_start)


def _read_long_take(
    path: Path,
    layout: _Layout,
    parsed: dict[str, np.ndarray],
    points: np.ndarray,
    residuals: np.ndarray,
    declared: int,
    name: str,
) -> tuple[np.ndarray, np.ndarray]:
    """All ``declared`` frames of the marker, from the file, checked against ezc3d's first ones."""
    labels = parsed["labels"]
    if layout.processor != _INTEL or layout.scale is None or layout.scale >= 0:
        raise InputFileError(
            f"{name} has {declared} frames, more than the {_EZC3D_MAX_FRAMES} the C3D reader "
            "reads, and is not in the float (Intel) format whose remaining frames can be read "
            "directly; export it as floats, as a shorter take, or as CSV"
        )
    if layout.n_points != len(labels):
        raise InputFileError(
            f"{name} is inconsistent: its header says {layout.n_points} markers per frame but it "
            f"labels {len(labels)}; export the take again"
        )
    frame_words = 4 * layout.n_points + layout.analog_per_frame
    data = np.fromfile(
        path,
        dtype="<f4",
        count=declared * frame_words,
        offset=(layout.data_start - 1) * 512,
    )
    if len(data) < declared * frame_words:
        raise InputFileError(f"{name} is truncated: it declares {declared} frames; export again")
    index = int(parsed["index"])
    cells = data.reshape(declared, frame_words)[:, 4 * index : 4 * index + 4].astype(np.float64)
    # The fourth word, a float, holds the residual (over the scale) in its integer's second byte
    # and the camera mask in its first, as ezc3d writes and reads it; negative means unseen.
    word = cells[:, 3]
    unseen = word < 0
    residual = ((np.where(unseen, 0, word).astype(np.int64) >> 8) & 0xFF) * -layout.scale
    residual[unseen] = -1.0
    full = np.where(unseen[:, None], np.nan, cells[:, :3])
    n = len(points)
    # Only trust this reading of the file if it reproduces every sample ezc3d read.
    same = np.array_equal(full[:n], points, equal_nan=True) and np.array_equal(
        residual[:n], residuals, equal_nan=True
    )
    if not same:
        raise InputFileError(
            f"{name} has {declared} frames, more than the {_EZC3D_MAX_FRAMES} the C3D reader "
            "reads, and the rest could not be read consistently; export a shorter take or use "
            "the CSV export"
        )
    return full, residual
