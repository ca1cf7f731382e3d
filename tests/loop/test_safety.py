import pytest

from drivers.errors import TravelLimitTrip, WatchdogTrip
from rt_ident.loop.safety import SafetyMonitor


def monitor(**kw):
    base = dict(lead=1e-3, window=(-0.01, 0.01), max_decel=1e3, watchdog_ticks=3)
    base.update(kw)
    return SafetyMonitor(**base)


def test_trips_on_predicted_stopping_distance_before_position_leaves_window_and_names_the_window_as_a_fix():
    m = monitor()
    # x = 5 mm, v = 5 mm/s per rad/s * 5 rad/s... use theta2 = 5 rad (x=5 mm), omega2 = 110 rad/s:
    # v = 0.11 m/s, a = 1 m/s^2 -> stopping distance 6.05 mm -> x_stop = 11.05 mm > 10 mm
    with pytest.raises(TravelLimitTrip, match="would stop") as e:
        m.check(10, theta1_last=0.1, theta2_last=5.0, omega2_last=110.0, torque_active=True)
    assert "safety.window" in e.value.fix and "excitation.peak" in e.value.fix


def test_same_position_moving_away_from_the_limit_does_not_trip():
    m = monitor()
    m.check(10, theta1_last=0.1, theta2_last=5.0, omega2_last=-110.0, torque_active=True)


def test_position_outside_window_trips_even_at_rest():
    with pytest.raises(TravelLimitTrip):
        monitor().check(10, theta1_last=0.1, theta2_last=-10.5, omega2_last=0.0, torque_active=False)


def test_watchdog_trips_after_configured_ticks_without_samples():
    m = monitor()
    m.check(0, 0, 0, 0, True)
    m.check(0, 0, 0, 0, True)
    with pytest.raises(WatchdogTrip, match="3 ticks") as e:
        m.check(0, 0, 0, 0, True)
    assert e.value.fix.startswith("the device's link") and "safety.watchdog_ticks" in e.value.fix


def test_fresh_samples_reset_the_watchdog():
    m = monitor()
    m.check(0, 0.0, 0, 0, True)
    m.check(0, 0.0, 0, 0, True)
    m.check(5, 0.2, 0, 0, True)
    m.check(0, 0.0, 0, 0, True)
    m.check(0, 0.0, 0, 0, True)
    assert m.stale_ticks == 2


def test_stuck_encoder_under_torque_trips_naming_the_encoder_and_the_stuck_torque():
    m = monitor()
    m.check(5, 0.25, 0, 0, True)
    m.check(5, 0.25, 0, 0, True)
    m.check(5, 0.25, 0, 0, True)
    with pytest.raises(WatchdogTrip, match="stuck") as e:
        m.check(5, 0.25, 0, 0, True)
    assert e.value.fix.startswith("the motor encoder") and "safety.stuck_torque" in e.value.fix
    assert WatchdogTrip.fix is None                                  # set on the trip, not on its class


def test_unchanged_encoder_without_torque_is_not_stuck():
    m = monitor()
    for _ in range(10):
        m.check(5, 0.25, 0, 0, False)


def test_reversed_window_rejected():
    with pytest.raises(ValueError, match="window"):
        monitor(window=(0.01, -0.01))


def test_a_speed_trip_names_a_slower_path_before_a_higher_limit():
    from drivers.errors import SpeedTrip

    m = monitor(max_speed=0.01)
    with pytest.raises(SpeedTrip, match="safety.max_speed_m_s") as e:
        m.check(10, theta1_last=0.1, theta2_last=0.0, omega2_last=20.0, torque_active=True)
    assert e.value.fix.index("[reference]") < e.value.fix.index("safety.max_speed_m_s")
