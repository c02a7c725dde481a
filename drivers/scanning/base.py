"""Scan readers: one per kind of scanner output, chosen by file suffix or format name.

Every reader turns a file (or a folder, or the bytes of an upload) into a :class:`ScanFile`: a
:class:`~recon.inputs.Scan` in metres plus what was left out. The public method
:meth:`ScanReader.read` lives here and does what every reader needs (argument checks, uploads
written to a temporary file, missing files); each reader implements ``_read``.

Formats (:data:`SCAN_READERS`, :data:`SCAN_SUFFIXES`):

========== =============================== ===============================================
format     suffixes                        reader
========== =============================== ===============================================
ply, pcd,  .ply .pcd .xyz .xyzn .xyzrgb    :class:`~drivers.scanning.pointcloud.PointCloudReader`
xyz, ...   .pts                            (Open3D)
e57        .e57                            :class:`~drivers.scanning.e57.E57Reader` (pye57)
rgbd       .rgbd.json, .zip, a folder      :class:`~drivers.scanning.rgbd.RGBDReader`
bag        .bag                            :class:`~drivers.scanning.bag.RealSenseBagReader`
========== =============================== ===============================================

Readers are registered in :data:`SCAN_READERS` (a :class:`~drivers.registry.Registry`) and
imported lazily, so a missing optional dependency is an error naming it, not an import failure of
the package. Options are a pydantic model per reader, selected by ``kind``.
"""

from __future__ import annotations

import contextlib
import tempfile
from abc import ABC, abstractmethod
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike
from pydantic import BaseModel, ConfigDict, ValidationError

from drivers.errors import InputFileError, UnknownFormatError
from drivers.registry import Registry
from drivers.units import metres_per
from recon.inputs import Scan

#: File suffix -> format name. The longest matching suffix wins (``.rgbd.json``).
SCAN_SUFFIXES: dict[str, str] = {
    ".ply": "ply",
    ".pcd": "pcd",
    ".xyz": "xyz",
    ".xyzn": "xyzn",
    ".xyzrgb": "xyzrgb",
    ".pts": "pts",
    ".e57": "e57",
    ".rgbd.json": "rgbd",
    ".zip": "rgbd",
    ".bag": "bag",
}

#: The format of a folder given as a scan.
FOLDER_FORMAT = "rgbd"


#: Why a point cloud's reader leaves points out.
DROPPED_NOT_FINITE = "without finite coordinates"
#: Why depth-image readers leave measurements out.
DROPPED_DEPTH = "with no depth or a depth beyond depth_trunc_m"


@dataclass(frozen=True)
class ScanFile:
    """A scan read from a file.

    Attributes
    ----------
    scan : Scan
        In metres.
    format : str
        The format name it was read as (a name in :data:`SCAN_READERS`).
    n_dropped : int
        Points left out: without finite coordinates (organised clouds mark holes with NaN), or
        depth measurements outside the accepted range.
    notes : tuple of str
        What the reader did that a user may want to know (frames fused, depth scale used).
    dropped_because : str
        Why the reader left the ``n_dropped`` points out, in words that follow "left out".
    """

    scan: Scan
    format: str
    n_dropped: int
    notes: tuple[str, ...] = ()
    dropped_because: str = DROPPED_NOT_FINITE


class ReaderOptions(BaseModel):
    """Options of a reader; each reader subclasses it with a literal ``kind``."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    kind: str


class ScanReader(ABC):
    """Reads one kind of scanner output into a :class:`ScanFile`.

    Parameters
    ----------
    options : ReaderOptions, optional
        An instance of the reader's :attr:`options_class`; default options if omitted.

    Raises
    ------
    ValueError
        Options of another reader.
    """

    #: Registry name of the reader.
    kind: ClassVar[str]
    #: Its options model.
    options_class: ClassVar[type[ReaderOptions]]
    #: Whether the format fixes its length unit (E57 is metres by its standard; depth images
    #: carry a depth scale), so ``units`` other than metres would be a contradiction.
    fixed_units: ClassVar[bool] = False
    #: Whether the reader takes a folder as well as a file.
    accepts_folders: ClassVar[bool] = False

    def __init__(self, options: ReaderOptions | None = None) -> None:
        if options is None:
            options = self.options_class.model_validate({})
        if not isinstance(options, self.options_class):
            raise ValueError(
                f"the {self.kind} reader takes {self.options_class.__name__}, got "
                f"{type(options).__name__} (kind {getattr(options, 'kind', '?')!r})"
            )
        self.options = options
        #: Bounds set by whoever runs the reader (see :func:`make_reader`), and the names of the
        #: settings behind them, for messages.
        self.limits: dict[str, float] = {}
        self.limit_names: dict[str, str] = {}

    def limit_source(self, name: str) -> str:
        """What sets the resource option ``name`` here, for a message saying what to change.

        The setting behind the caller's bound when the option is at that bound, else the option.
        """
        setting = self.limit_names.get(name)
        if setting is not None and getattr(self.options, name, None) == self.limits.get(name):
            return setting
        return f"the reader option {name}"

    def read(
        self,
        source: str | Path | bytes,
        *,
        fmt: str,
        units: str = "m",
        name: str | None = None,
    ) -> ScanFile:
        """Read a scan.

        Parameters
        ----------
        source : path or bytes
            The file or folder, or an upload's content.
        fmt : str
            The format name (one this reader is registered for).
        units : {"m", "mm"}
            Length unit of the coordinates, for formats that do not fix it.
        name : str, optional
            File name of an upload, for its suffix and for messages.

        Raises
        ------
        InputFileError
            Missing, unreadable, empty or inconsistent input.
        ValueError
            An unknown unit, or a unit other than metres for a format that fixes its own.
        """
        scale = metres_per(units)
        if self.fixed_units and units != "m":
            raise ValueError(
                f"{fmt.upper()} input fixes its own length unit ({self._unit_note()}); "
                f"leave units at 'm' instead of {units!r}"
            )
        label = name or ("upload" if isinstance(source, bytes) else str(source))
        with self._materialised(source, fmt, label) as path:
            return self._read(path, fmt=fmt, label=label, scale=scale)

    @abstractmethod
    def _read(self, path: Path, *, fmt: str, label: str, scale: float) -> ScanFile:
        """Read ``path`` (an existing file, or a folder if :attr:`accepts_folders`).

        ``scale`` is metres per unit of the coordinates; ``label`` names the input in messages.
        """

    def _unit_note(self) -> str:
        return "metres"

    def _upload_suffix(self, fmt: str) -> str:
        """Suffix of the temporary file an upload is written to (some libraries look at it)."""
        return f".{fmt}"

    @contextlib.contextmanager
    def _materialised(self, source: str | Path | bytes, fmt: str, label: str) -> Iterator[Path]:
        # Open3D, libe57 and librealsense read files only: uploads go to a temporary file.
        if isinstance(source, bytes):
            with tempfile.TemporaryDirectory(prefix="teachpath-scan-") as tmp:
                path = Path(tmp) / f"upload{self._upload_suffix(fmt)}"
                path.write_bytes(source)
                yield path
            return
        path = Path(source)
        if path.is_dir() and self.accepts_folders:
            yield path
            return
        if path.is_dir():
            raise InputFileError(f"{label} is a folder, not a {fmt.upper()} file")
        if not path.is_file():
            raise InputFileError(f"{label} does not exist or is not a file")
        yield path


#: Scan readers by format name, imported on first use; packages add formats through the
#: entry-point group ``teachpath.scan_readers`` (a plugin format is chosen explicitly, or by a
#: file suffix equal to its name, e.g. ``.las`` for ``las``).
SCAN_READERS: Registry[type[ScanReader]] = Registry(
    "scan format",
    {
        "ply": "drivers.scanning.pointcloud:PointCloudReader",
        "pcd": "drivers.scanning.pointcloud:PointCloudReader",
        "xyz": "drivers.scanning.pointcloud:PointCloudReader",
        "xyzn": "drivers.scanning.pointcloud:PointCloudReader",
        "xyzrgb": "drivers.scanning.pointcloud:PointCloudReader",
        "pts": "drivers.scanning.pointcloud:PointCloudReader",
        "e57": "drivers.scanning.e57:E57Reader",
        "rgbd": "drivers.scanning.rgbd:RGBDReader",
        "bag": "drivers.scanning.bag:RealSenseBagReader",
    },
    group="teachpath.scan_readers",
    unknown_error=UnknownFormatError,
    base=ScanReader,
)


def format_for(name: str, explicit: str | None = None) -> str:
    """The scan format of a file, from ``explicit`` or the file's suffix.

    Parameters
    ----------
    name : str
        File name (only its suffix is used).
    explicit : str, optional
        A format name (one of :data:`SCAN_READERS`), with or without a leading dot.

    Raises
    ------
    UnknownFormatError
        No such format, or a suffix that names none.
    """
    if explicit is not None:
        fmt = explicit.lower().lstrip(".")
        if fmt not in SCAN_READERS:
            raise SCAN_READERS.unknown(explicit)
        return fmt
    lowered = Path(name).name.lower()
    for suffix in sorted(SCAN_SUFFIXES, key=len, reverse=True):
        if lowered.endswith(suffix) and len(lowered) > len(suffix):
            return SCAN_SUFFIXES[suffix]
    plugin = Path(lowered).suffix.lstrip(".")
    if plugin and plugin in SCAN_READERS:
        return plugin
    known = SCAN_READERS.names()
    raise UnknownFormatError(
        f"cannot tell the scan format of {name!r} from its suffix; name the file with one of "
        f"{', '.join(sorted(SCAN_SUFFIXES))} (or give a folder of RGB-D frames), or give the "
        f"format explicitly ({', '.join(known)})"
    )


def reader_class(fmt: str) -> type[ScanReader]:
    """The reader class registered for format ``fmt``.

    Raises
    ------
    UnknownFormatError
        Unknown format (the message lists the known ones).
    MissingDependencyError
        The reader's third-party dependency is not installed (a subclass of
        UnknownFormatError; the message says what to install).
    """
    return SCAN_READERS.load(fmt)


def make_reader(
    fmt: str,
    options: ReaderOptions | Mapping[str, Any] | None = None,
    limits: Mapping[str, float] | None = None,
    limit_names: Mapping[str, str] | None = None,
) -> ScanReader:
    """A reader for ``fmt`` with ``options`` (a model instance, or a mapping validated into one).

    Parameters
    ----------
    fmt : str
    options : ReaderOptions or mapping, optional
    limits : mapping, optional
        Upper bounds for resource options (e.g. ``{"max_unpacked_mb": 2048, "timeout_s":
        300}``), set by whoever runs the reader for someone else (the service): a default above
        a bound is lowered to it, a value asked for above it is refused. Options the reader
        does not have are ignored.
    limit_names : mapping, optional
        The setting behind each bound (e.g. ``{"max_pixels": "TEACHPATH_MAX_SCAN_PIXELS"}``),
        named in the messages of a reader refusing an input past it.

    Raises
    ------
    UnknownFormatError
        Unknown format.
    ValueError
        Options that do not fit the reader (another reader's, unknown or invalid fields), or
        past a limit.
    """
    cls = reader_class(fmt)
    if isinstance(options, Mapping):
        values = dict(options)
        kind = values.setdefault("kind", cls.kind)
        if kind != cls.kind:
            raise ValueError(
                f"options of kind {kind!r} given for a {fmt!r} scan, which the {cls.kind!r} "
                "reader reads"
            )
        try:
            options = cls.options_class(**values)
        except ValidationError as exc:
            problems = "; ".join(
                f"{'.'.join(str(p) for p in err['loc']) or 'options'}: {err['msg']}"
                for err in exc.errors()
            )
            raise ValueError(f"invalid {cls.kind} reader options: {problems}") from None
    names = dict(limit_names or {})
    if limits:
        options = _within_limits(options or cls.options_class.model_validate({}), limits, names)
    reader = cls(options)
    reader.limits, reader.limit_names = dict(limits or {}), names
    return reader


def _within_limits(
    options: ReaderOptions, limits: Mapping[str, float], names: Mapping[str, str]
) -> ReaderOptions:
    lowered = {}
    for name, limit in limits.items():
        value = getattr(options, name, None)
        if value is None or value <= limit:
            continue
        if name in options.model_fields_set:
            setting = f" ({names[name]})" if name in names else ""
            raise ValueError(
                f"option {name}={value:g} exceeds the limit of {limit:g} here{setting}; ask for "
                f"at most {limit:g} (send a smaller scan, or fewer frames)"
            )
        # The option's type: a bound given as a float lowers an integer option to an integer.
        lowered[name] = type(value)(limit)
    return options.model_copy(update=lowered) if lowered else options


def read_scan(
    source: str | Path | bytes,
    *,
    units: str = "m",
    fmt: str | None = None,
    name: str | None = None,
    options: ReaderOptions | Mapping[str, Any] | None = None,
    limits: Mapping[str, float] | None = None,
    limit_names: Mapping[str, str] | None = None,
) -> ScanFile:
    """Read a scan in any registered format.

    Parameters
    ----------
    source : path or bytes
        A file or a folder (RGB-D frames), or an upload's content (then ``name`` or ``fmt``
        gives the format).
    units : {"m", "mm"}
        Length unit of point-cloud coordinates. E57, RGB-D and bag input fix their own unit, so
        only "m" is accepted for them.
    fmt : str, optional
        Format name (see :data:`SCAN_READERS`); default from the suffix, or "rgbd" for a folder.
    name : str, optional
        File name of an upload, for its suffix and for messages.
    options : ReaderOptions or mapping, optional
        Reader options (e.g. ``{"depth_trunc_m": 1.5}`` for RGB-D); default options if omitted.
    limits : mapping, optional
        Upper bounds for resource options (see :func:`make_reader`).
    limit_names : mapping, optional
        The settings behind those bounds, for messages (see :func:`make_reader`).

    Returns
    -------
    ScanFile

    Raises
    ------
    InputFileError
        Missing, unreadable, empty or inconsistent input; the message says what to change.
    InputTooLargeError
        An input past a resource bound (an RGB-D frame with more pixels than allowed); the
        message names the bound and what sets it.
    UnknownFormatError
        Unknown format or suffix, or a reader whose dependency is missing.
    ValueError
        An unknown unit, or options that do not fit the reader.
    """
    if fmt is None and name is None and not isinstance(source, bytes) and Path(source).is_dir():
        fmt = FOLDER_FORMAT
    fmt = format_for(name or ("" if isinstance(source, bytes) else str(source)), fmt)
    reader = make_reader(fmt, options, limits, limit_names)
    scan_file = reader.read(source, fmt=fmt, units=units, name=name)
    check_scan_units(scan_file.scan.points_m, units, name or fmt)
    return scan_file


#: A scan wider than this is not of a workpiece in a robot's cell (a depth camera sees a few
#: metres; the corpus's room and plant scans span 2-7.5 m).
MAX_SCAN_EXTENT_M = 30.0
#: Nor one with points this far from the scanner's origin (geographic coordinates).
MAX_SCANNER_DISTANCE_M = 100.0
#: A scan narrower than this, read as millimetres, is metres read as millimetres.
MIN_SCAN_EXTENT_MM_M = 1e-3


def check_scan_units(points_m: ArrayLike, units: str, label: str) -> None:
    """Refuse at reading a scan whose size says its numbers are in another unit, or that is
    not of a workpiece at all, rather than at the first reconstruction.

    Parameters
    ----------
    points_m : ndarray of shape (N, 3), metres as read
    units : {"m", "mm"}
        The unit the coordinates were read in.
    label : str
        The file, for the message.

    Raises
    ------
    UnitsMismatchError
        Millimetres read as metres (a part of 170 mm read as 170 m), metres read as
        millimetres (a scan narrower than a millimetre), or a scan of a site (wider than
        :data:`MAX_SCAN_EXTENT_M`, or in geographic coordinates).
    """
    from recon.errors import UnitsMismatchError

    points = np.asarray(points_m)
    if len(points) == 0:
        return
    # Of the bulk (0.5-99.5 % on each axis): a few stray points far out do not refuse a scan.
    lo, hi = np.percentile(points, [0.5, 99.5], axis=0)
    with np.errstate(over="ignore", invalid="ignore"):  # a file's 1e300: inf, refused below
        extent_m = float(np.linalg.norm(hi - lo))
        farthest_m = float(np.percentile(np.abs(points).max(axis=1), 99.5))
    if extent_m > MAX_SCAN_EXTENT_M or farthest_m > MAX_SCANNER_DISTANCE_M:
        said = (
            f"the scan {label}, read as {'millimetres' if units == 'mm' else 'metres'}, spans "
            f"{extent_m:.4g} m and reaches {farthest_m:.4g} m from its origin"
        )
        # As millimetres it would be a workpiece within a few metres of the scanner.
        in_mm_fits = (
            1e-3 * max(extent_m, farthest_m) <= MAX_SCAN_EXTENT_M
            and 1e-3 * extent_m >= MIN_SCAN_EXTENT_MM_M
        )
        if units == "m" and in_mm_fits:
            raise UnitsMismatchError(
                f"{said}: its numbers look like millimetres (it would span "
                f"{extent_m:.4g} mm); upload it with its units set to mm (units=mm, --units mm)"
            )
        raise UnitsMismatchError(
            f"{said}: that is a scan of a site, not of a workpiece in a robot's cell; crop it to "
            "the workpiece, with coordinates near the scanner, and upload that"
        )
    if units == "mm" and extent_m < MIN_SCAN_EXTENT_MM_M:
        raise UnitsMismatchError(
            f"the scan {label}, read as millimetres, spans only {extent_m * 1e3:.3g} mm: if its "
            f"numbers are metres it spans {extent_m * 1e3:.3g} m; upload it with its units set "
            "to m (units=m, --units m)"
        )
