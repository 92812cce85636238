"""The operating box of a calibrated profile: the base's stated bounds kept, widened to hold the recordings."""

from __future__ import annotations

import pytest

from service.calibration import calibrate_from_base, stated_bounds
from synth.calibration import calibrate
from tests.calibration_data import BASE, healthy_drive


@pytest.fixture(scope="module")
def identified():
    return calibrate([healthy_drive()], BASE)


def test_stated_limits_are_kept_where_wider_and_widened_where_the_recordings_need_more(identified):
    recorded = identified.bounds
    wider_steer = recorded.steer_max_rad + 0.15
    narrower_r = 0.5 * recorded.r_max_radps
    result = stated_bounds(
        identified, {"steer_max_rad": wider_steer, "r_min_radps": -narrower_r, "r_max_radps": narrower_r}
    )
    box = result.bounds
    assert box.steer_max_rad == pytest.approx(wider_steer)  # kept: wider than the recordings need
    assert (box.r_min_radps, box.r_max_radps) == (recorded.r_min_radps, recorded.r_max_radps)  # widened
    # what the base does not state is the recordings' box
    assert (box.vx_min_mps, box.vx_max_mps, box.vy_max_mps) == (
        recorded.vx_min_mps,
        recorded.vx_max_mps,
        recorded.vy_max_mps,
    )
    assert result.notes[-1] == (
        "operating box: the base's bounds kept, widened to hold the recordings in r_max_radps, r_min_radps"
    )
    assert result.params == identified.params and result.estimates == identified.estimates


@pytest.mark.parametrize(
    ("given", "message"),
    [({"steer_max_rad": 2.0}, "steer_max_rad"), ({"vx_min_mps": -1.0}, "vx_min_mps"), ([0.3], "object")],
)
def test_an_invalid_stated_box_is_refused_with_its_field(identified, given, message):
    with pytest.raises(ValueError, match=message):
        stated_bounds(identified, given)


def test_the_profile_of_a_base_with_bounds_is_designed_on_the_stated_box():
    """calibrate_from_base (the CLI's and the REST endpoint's path) passes the base's bounds: the profile and its
    gains are designed on the wider steering limit, not on the recordings' box."""
    report = calibrate_from_base([healthy_drive()], {"params": BASE, "bounds": {"steer_max_rad": 0.4}})
    assert report.profile.bounds.steer_max_rad == pytest.approx(0.4)
    assert report.gains.bounds.steer_max_rad == pytest.approx(0.4)
    assert "operating box: the base's bounds kept" in report.calibration.notes[-1]
