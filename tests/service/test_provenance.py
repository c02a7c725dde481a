"""What makes a stored reconstruction or plan outdated (service/provenance.py)."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from types import SimpleNamespace

from service.provenance import reconstruction_outdated, trajectory_outdated

T0 = datetime(2026, 12, 6, 12, 0, tzinfo=UTC)
EYE = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]


def _row(id_, minutes, inputs=None, params=None):
    return SimpleNamespace(
        id=id_, created_at=T0 + timedelta(minutes=minutes), inputs=inputs or {}, params=params or {}
    )


class _Store:
    def __init__(self, *rows):
        self.rows = {r.id: r for r in rows}

    def artifact(self, artifact_id, kind=None):
        return self.rows.get(artifact_id)

    def artifacts(self, session_id, kind=None):
        return [r for r in self.rows.values() if r.id.startswith("tch")]


def _session(recording="rec_a", scan="scn_a", T=EYE):
    return SimpleNamespace(id="ses", recording_id=recording, scan_id=scan, T_base_tracker=T)


def test_inputs_named_on_purpose_and_older_than_the_result_are_no_change():
    """A reconstruction of an older trace named in the request (the session's trace is newer
    than the trace, but older than the reconstruction) is not outdated: nothing changed since."""
    rec_a, rec_b, scan = _row("rec_a", 0), _row("rec_b", 5), _row("scn_a", 0)
    recon = _row("rcn", 10, {"recording_id": "rec_a", "scan_id": "scn_a"})
    store = _Store(rec_a, rec_b, scan, recon)
    assert reconstruction_outdated(store, _session(recording="rec_b"), recon) == []
    # A trace added after it is a change.
    store.rows["rec_c"] = _row("rec_c", 20)
    (reason,) = reconstruction_outdated(store, _session(recording="rec_c"), recon)
    assert reason.startswith("the trace") and "rec_c" in reason


def test_a_scan_added_after_a_reconstruction_without_one_is_a_change():
    recon = _row("rcn", 10, {"recording_id": "rec_a", "scan_id": None})
    store = _Store(_row("rec_a", 0), recon, _row("scn_b", 15))
    (reason,) = reconstruction_outdated(store, _session(scan="scn_b"), recon)
    assert "made with none" in reason and "scn_b" in reason


def test_a_calibration_set_after_a_plan_made_without_one_is_a_change():
    recon = _row("rcn", 10, {"recording_id": "rec_a", "scan_id": "scn_a"})
    plan = _row("trj", 11, {"reconstruction_id": "rcn"}, {"T_base_tracker": None})
    store = _Store(_row("rec_a", 0), _row("scn_a", 0), recon, plan)
    (reason,) = trajectory_outdated(store, _session(), plan)
    assert "made without one" in reason
    planned = _row("trj2", 11, {"reconstruction_id": "rcn"}, {"T_base_tracker": EYE})
    assert trajectory_outdated(store, _session(), planned) == []
    moved = [row[:] for row in EYE]
    moved[2][3] = 0.003
    (reason,) = trajectory_outdated(store, _session(T=moved), planned)
    assert "3.0 mm" in reason


def test_touches_added_after_a_reconstruction_made_without_them_are_a_change():
    recon = _row(
        "rcn", 10, {"recording_id": "rec_a", "scan_id": "scn_a"}, {"touches_considered": True}
    )
    store = _Store(_row("rec_a", 0), _row("scn_a", 0), recon)
    assert reconstruction_outdated(store, _session(), recon) == []
    store.rows["tch_a"] = _row("tch_a", 20)
    (reason,) = reconstruction_outdated(store, _session(), recon)
    assert reason.startswith("the touches") and "tch_a" in reason
    # Touches older than it (it was made not to use them) are no change; nor are touches
    # when it was asked not to use any.
    store.rows["tch_a"] = _row("tch_a", 5)
    assert reconstruction_outdated(store, _session(), recon) == []
    store.rows["tch_a"] = _row("tch_a", 20)
    # Touches that could not have placed it (declined, no scan, registration off, the trace
    # alone) are no change either.
    declined = _row("rcn2", 10, {"recording_id": "rec_a", "scan_id": "scn_a"})
    declined.params = {"touches_considered": False}
    assert reconstruction_outdated(store, _session(), declined) == []
    # One made by an earlier version (nothing recorded): judged from its parameters.
    for params, outdated in (
        ({"alpha": "auto", "register": True}, True),
        ({"alpha": 1.0, "register": True}, False),
        ({"alpha": 0.5, "register": False}, False),
    ):
        old = _row("rcn3", 10, {"recording_id": "rec_a", "scan_id": "scn_a"}, params)
        assert bool(reconstruction_outdated(store, _session(), old)) is outdated, params
