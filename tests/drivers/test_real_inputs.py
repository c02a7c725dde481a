"""Files written by real trackers, from the shared corpus (``../shared/corpus/real-inputs``, its
PROVENANCE.md says where each comes from). Skipped, saying so, where the corpus is absent."""

from __future__ import annotations

import pytest

from drivers.errors import InputFileError
from drivers.tracking.c3d import read_c3d
from drivers.tracking.readers import read_trace
from tests.corpus import require_corpus


@pytest.fixture(scope="module")
def real_inputs():
    return require_corpus() / "real-inputs"


def test_an_optotrak_c3d_that_declares_1149_frames_and_holds_29_is_read_with_a_note(real_inputs):
    """NDI's software writes frames 1-1149 in the header of a 29-frame export: it was refused
    as truncated. The 29 frames are read, and the note says what the header claimed."""
    trace = read_c3d(real_inputs / "c3d" / "optotrak_ezc3d_test.c3d", marker="Marker_1")
    assert len(trace) == 29 and trace.rate_hz == 30.0 and trace.units == "mm"
    assert "header says 1149 frames" in trace.notes[0] and "29 were read" in trace.notes[0]
    raw = read_trace(real_inputs / "c3d" / "optotrak_ezc3d_test.c3d", marker="Marker_1").raw
    assert raw.meta["notes"] == list(trace.notes)


def test_a_motive_3_export_of_unlabeled_markers_asks_and_says_which_markers_moved(real_inputs):
    """18 unlabeled markers, none of them a pen: the refusal ranks them by how far they moved
    (all under 5 mm here), instead of a pick of one that barely moves."""
    path = real_inputs / "motive_csv" / "nmotive3_unlabeled_markers_360hz_mm.csv"
    with pytest.raises(InputFileError) as refused:
        read_trace(path)
    message = str(refused.value)
    assert "name the pen-tip marker" in message
    assert "The markers that moved most: Unlabeled" in message
    assert "18 moved less than 5 mm" in message
