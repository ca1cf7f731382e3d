import importlib.util
from pathlib import Path

spec = importlib.util.spec_from_file_location("track_step", Path(__file__).parents[2] / "tools" / "track_step.py")
track_step = importlib.util.module_from_spec(spec)
spec.loader.exec_module(track_step)


def test_forgetting_tracks_a_20_percent_damping_step_within_half_a_second():
    r = track_step.track(0.7, 0.2, 0.02, after=40)
    assert r["settle_s"] is not None and r["settle_s"] < 0.5
    assert abs(r["final_error_pct"]) < 2


def test_without_forgetting_the_estimate_stays_a_blend_of_old_and_new():
    r = track_step.track(1.0, 0.2, 0.02, after=40)
    assert r["settle_s"] is None
