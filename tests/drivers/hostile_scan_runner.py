"""Read scan files one after another and print one JSON line per outcome (for
``test_scan_reader_hostile``).

Run as ``python -m tests.drivers.hostile_scan_runner FILE...``. Each file is announced before it
is read, so when native code kills the process the test sees which file did it, and one process
reads them all (Open3D is imported once, not once per file).
"""

from __future__ import annotations

import json
import sys

from drivers.scanning.base import read_scan


def main(paths: list[str]) -> None:
    for path in paths:
        print(json.dumps({"start": path}), flush=True)
        try:
            scan = read_scan(path)
        except Exception as exc:  # every outcome is reported; the test judges it
            outcome = {"error": type(exc).__name__, "message": str(exc)}
        else:
            outcome = {"error": None, "points": len(scan.scan)}
        print(json.dumps({"done": path, **outcome}), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
