"""A UR arm's own kinematics calibration, as its controller stores it (``calibration.conf``).

Every UR arm is calibrated at the factory; the controller keeps the offsets to the nominal DH
parameters in ``/root/.urcontrol/calibration.conf`` (copy it off the controller, e.g. with
``scp``), an INI file whose ``[mounting]`` section holds one bracketed list of six numbers per
parameter::

    [mounting]
    delta_theta = [ -2.4e-07, 1.6023, -1.6861, 0.0837, -1.0e-07, 3.9e-08 ]
    delta_a = [ 2.1e-05, 0.6320, 0.0023, -4.6e-05, -6.4e-05, 0 ]
    delta_d = [ -1.6e-04, 439.14, -446.03, 6.8862, -3.9e-05, -8.8e-04 ]
    delta_alpha = [ -6.5e-04, 0.0014, 0.0069, -8.1e-04, 4.1e-04, 0 ]

(radians and metres; other keys and sections are ignored). :func:`read_ur_calibration` gives the
:class:`recon.kinematics.DHCalibration`; :func:`recon.kinematics.with_calibration` then checks
it against the arm's nominal model.
"""

from __future__ import annotations

import configparser
from pathlib import Path

import numpy as np

from drivers.errors import InputFileError, clipped
from recon.kinematics import DHCalibration

#: A calibration.conf is a few kilobytes; anything much larger is not one.
MAX_BYTES = 256 * 1024
#: The keys of the ``[mounting]`` section read, and the DHCalibration fields they fill.
KEYS = {
    "delta_theta": "delta_theta_rad",
    "delta_a": "delta_a_m",
    "delta_d": "delta_d_m",
    "delta_alpha": "delta_alpha_rad",
}
SECTION = "mounting"


def read_ur_calibration(source: str | Path | bytes, *, name: str | None = None) -> DHCalibration:
    """Read a controller's ``calibration.conf``.

    Parameters
    ----------
    source : path or bytes
    name : str, optional
        What to call it in messages and in the plan's report (default: the file's name).

    Returns
    -------
    DHCalibration

    Raises
    ------
    InputFileError
        Missing, too large, not text, not an INI file, no ``[mounting]`` section, a key
        missing, or a value that is not six finite numbers.
    """
    label = name or (Path(source).name if not isinstance(source, bytes) else "calibration")
    text = _text(source, label)
    parser = configparser.ConfigParser(interpolation=None, strict=False)
    try:
        parser.read_string(text, source=label)
    except configparser.Error as exc:
        raise InputFileError(
            f"{label} is not a UR calibration file (an INI file with a [{SECTION}] section): "
            f"{clipped(str(exc).splitlines()[0])}; copy /root/.urcontrol/calibration.conf off "
            "the controller"
        ) from None
    if not parser.has_section(SECTION):
        raise InputFileError(
            f"{label} has no [{SECTION}] section: a controller's calibration.conf has one with "
            f"{', '.join(KEYS)}"
        )
    values = {}
    for key, field_name in KEYS.items():
        if not parser.has_option(SECTION, key):
            raise InputFileError(f"{label}: [{SECTION}] has no {key} (six numbers expected)")
        values[field_name] = _six_numbers(parser.get(SECTION, key), f"{label}: {key}")
    try:
        return DHCalibration(**values, source=label)
    except ValueError as exc:
        raise InputFileError(f"{label}: {exc}") from None


def _text(source: str | Path | bytes, label: str) -> str:
    if isinstance(source, bytes):
        raw = source
    else:
        path = Path(source)
        try:
            size = path.stat().st_size
            if size > MAX_BYTES:
                raise InputFileError(
                    f"{label} is {size} bytes; a UR calibration file is a few kilobytes"
                )
            raw = path.read_bytes()
        except OSError as exc:
            raise InputFileError(f"cannot read the calibration {label}: {exc.strerror}") from None
    if len(raw) > MAX_BYTES:
        raise InputFileError(f"{label} is {len(raw)} bytes; a UR calibration file is a few kB")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        raise InputFileError(
            f"{label} is not text: give the controller's calibration.conf"
        ) from None


def _six_numbers(value: str, label: str) -> np.ndarray:
    """``[ a, b, c, d, e, f ]`` (brackets optional) as six finite floats."""
    inner = value.strip()
    if inner.startswith("[") and inner.endswith("]"):
        inner = inner[1:-1]
    parts = [p for p in inner.replace(",", " ").split() if p]
    try:
        numbers = np.array([float(p) for p in parts], dtype=np.float64)
    except ValueError:
        raise InputFileError(f"{label} is not six numbers: {clipped(value)!r}") from None
    if numbers.shape != (6,) or not np.all(np.isfinite(numbers)):
        raise InputFileError(
            f"{label} must be six finite numbers (one per joint), got {clipped(value)!r}"
        )
    return numbers
