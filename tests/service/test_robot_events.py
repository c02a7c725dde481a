"""What makes the arm's event stream send at once, besides a new reading of the arm: the run
that owns the arm, and its speed (a run ended with the arm at rest sends no new reading, and the
safety bar said "busy" until the next keep-alive)."""

from __future__ import annotations

from types import SimpleNamespace

from service.api.robot import _run_signature


class _Runner:
    def __init__(self, running: bool, **speed) -> None:
        self.running = running
        self._speed = {"speed_fraction": 1.0, "paused": False, "speed_now": 1.0, **speed}

    def speed_view(self) -> dict:
        return dict(self._speed)


def _services(**runners) -> SimpleNamespace:
    return SimpleNamespace(live=SimpleNamespace(executions=runners))


def test_the_owner_ending_changes_the_signature():
    running = _run_signature(_services(exe_a=_Runner(True)))
    assert running is not None and running[0] == "exe_a"
    assert _run_signature(_services(exe_a=_Runner(False))) is None
    assert _run_signature(_services()) is None


def test_a_speed_a_pause_and_coming_to_rest_change_the_signature():
    base = _run_signature(_services(exe_a=_Runner(True)))
    assert _run_signature(_services(exe_a=_Runner(True, speed_fraction=0.5))) != base
    pausing = _run_signature(_services(exe_a=_Runner(True, paused=True, speed_now=0.4)))
    at_rest = _run_signature(_services(exe_a=_Runner(True, paused=True, speed_now=0.0)))
    assert len({base, pausing, at_rest}) == 3
    # The ramp's every step is not an event of its own (the arm's readings carry those).
    assert _run_signature(_services(exe_a=_Runner(True, speed_now=0.7))) == base
