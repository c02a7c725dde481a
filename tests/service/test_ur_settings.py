"""The real arm's link settings: from the service's settings (or its environment) into the
ur_rtde backend, the same for the arm's monitor, each run and a recovered run."""

import pytest
from pydantic import ValidationError

from service.robot import ur_rtde_config
from tests.service.conftest import make_settings


def test_the_arm_s_settings_reach_its_backend(tmp_path, monkeypatch):
    monkeypatch.setenv("TEACHPATH_UR_WATCHDOG_HZ", "0.5")
    monkeypatch.setenv("TEACHPATH_UR_RT_PRIORITY", "0")
    monkeypatch.setenv("TEACHPATH_UR_STALE_AFTER_S", "2")
    settings = make_settings(tmp_path, ur_host="127.0.0.9", ur_robot="ur10e")
    config = ur_rtde_config(settings)
    assert (config.host, config.robot) == ("127.0.0.9", "ur10e")
    assert (config.watchdog_hz, config.rt_priority, config.stale_after_s) == (0.5, 0, 2.0)
    # A recovered run is judged with its own plan's arm model.
    assert ur_rtde_config(settings, robot="ur5e").robot == "ur5e"


def test_the_defaults_are_a_real_controller_s(tmp_path):
    config = ur_rtde_config(make_settings(tmp_path, ur_host="127.0.0.9"))
    assert (config.watchdog_hz, config.rt_priority, config.stale_after_s) == (2.0, 80, 0.5)


@pytest.mark.parametrize(
    "setting, message",
    [
        ({"ur_watchdog_hz": 0.1}, "ur_watchdog_hz"),  # 10 s of silence before the arm stops
        ({"ur_watchdog_hz": 1e9}, "ur_watchdog_hz"),
        ({"ur_watchdog_hz": float("nan")}, "ur_watchdog_hz"),
        ({"ur_rt_priority": 100}, "ur_rt_priority"),
        ({"ur_stale_after_s": 0.0}, "ur_stale_after_s"),
        ({"ur_stale_after_s": 60.0}, "ur_stale_after_s"),
        ({"ur_rt_priority": -1}, "ur_rt_priority"),
    ],
)
def test_settings_a_controller_could_not_take_stop_the_start(tmp_path, setting, message):
    with pytest.raises(ValidationError) as refused:
        make_settings(tmp_path, ur_host="127.0.0.9", **setting)
    assert message in str(refused.value)
