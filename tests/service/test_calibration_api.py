"""POST /profiles/{name}/calibration on the real service: recordings in, a proposed profile out, applied by a PUT."""

from __future__ import annotations

import pytest

from tests.calibration_data import BASE, csv_text, healthy_drive
from tests.service.helpers import job_done, make_settings, running, wait_for

pytestmark = pytest.mark.network


@pytest.fixture(scope="module")
def recording_csv() -> str:
    return csv_text(healthy_drive())


def test_calibration_proposes_a_profile_that_a_put_applies(tmp_path, recording_csv):
    settings = make_settings(tmp_path)
    body = {"base": {"params": BASE}, "recordings": [{"name": "drive-1.csv", "csv": recording_csv}]}
    with running(settings) as srv:
        assert srv.http.post("/profiles/car/calibration", json=body).status_code == 401  # the token is needed
        answer = srv.http.post("/profiles/car/calibration", json=body, headers=srv.auth, timeout=120.0)
        assert answer.status_code == 200, answer.text
        proposal = answer.json()
        assert proposal["profile_name"] == "car"
        params = proposal["profile"]["params"]
        assert params["effective_mass_kg"] == pytest.approx(1290.0, rel=0.01)
        assert params["cornering_drag"] is True and params["mass_kg"] == BASE["mass_kg"]
        report = proposal["report"]
        low, high = report["estimates"]["front_cornering_stiffness_npr"]["ci95"]
        assert low < 80000.0 < high
        assert report["gust"]["force_n"] == 800.0 and report["thresholds"]["steer"]["set_by"] == "gust"
        alarms = proposal["profile"]["alarms"]
        assert alarms["torque_warn_nm"] == report["thresholds"]["torque"]["warn"] < alarms["torque_fault_nm"]
        # proposed, not applied: the service knows no profile 'car' yet
        assert srv.get("/profiles/car").status_code == 404
        applied = srv.http.put("/profiles/car", json=proposal["profile"], headers=srv.auth)
        assert applied.status_code == 202, applied.text
        job = wait_for(lambda: job_done(srv, applied.json()["job"]), what="the calibrated profile's design")
        assert job["status"] == "succeeded"
        info = srv.get("/profiles/car").json()
        assert info["spec"]["params"]["effective_mass_kg"] == params["effective_mass_kg"]
        assert info["active_version"] == job["gain_version"]
        # a second calibration of the existing profile may leave out the base: the profile's own data sheet; this
        # one also enables the effectiveness stage, whose totals set the thresholds, and the service runs it
        again = srv.http.post(
            "/profiles/car/calibration",
            json={"recordings": [{"name": "drive-1.csv", "csv": recording_csv}], "effectiveness": True},
            headers=srv.auth,
            timeout=120.0,
        )
        assert again.status_code == 200, again.text
        staged = again.json()
        assert staged["profile"]["params"]["effective_mass_kg"] == pytest.approx(1290.0, rel=0.01)
        assert staged["profile"]["effectiveness"]["enabled"] is True
        assert staged["report"]["thresholds"]["torque"]["sigma"] > report["thresholds"]["torque"]["sigma"]
        applied = srv.http.put("/profiles/car", json=staged["profile"], headers=srv.auth)
        assert applied.status_code in (200, 202), applied.text
        assert srv.get("/profiles/car").json()["spec"]["effectiveness"]["enabled"] is True


def test_calibration_says_what_is_wrong(tmp_path, recording_csv):
    settings = make_settings(tmp_path)
    lines = recording_csv.splitlines()
    with running(settings) as srv:
        post = srv.http.post
        # no profile to take the data sheet from, and no base
        missing = post("/profiles/nobody/calibration", json={"recordings": [{"csv": recording_csv}]}, headers=srv.auth)
        assert missing.status_code == 404 and "give 'base'" in missing.json()["detail"]
        # a recording with a broken row is refused with its line number
        broken = "\n".join([*lines[:50], "0.49,15.0,nan,100,0.0", *lines[51:]])
        bad = post(
            "/profiles/car/calibration",
            json={"base": {"params": BASE}, "recordings": [{"name": "broken.csv", "csv": broken}]},
            headers=srv.auth,
            timeout=120.0,
        )
        assert bad.status_code == 422 and "broken.csv, line 51" in bad.json()["detail"]
        # a payload above the vehicle's mass is refused with the reason, a negative one is a bad body
        heavy = {"name": "heavy.csv", "csv": recording_csv, "payload_kg": 5000.0}
        too_heavy = post(
            "/profiles/car/calibration", json={"base": {"params": BASE}, "recordings": [heavy]}, headers=srv.auth
        )
        assert too_heavy.status_code == 422
        assert "refused: heavy.csv: a payload must be finite, 0 kg or more and at most" in too_heavy.json()["detail"]
        negative = {**heavy, "payload_kg": -1.0}
        bad_payload = post(
            "/profiles/car/calibration", json={"base": {"params": BASE}, "recordings": [negative]}, headers=srv.auth
        )
        assert bad_payload.status_code == 422 and "payload_kg" in bad_payload.text
        # a negative gust is a bad body
        gusty = post(
            "/profiles/car/calibration",
            json={"base": {"params": BASE}, "recordings": [{"csv": recording_csv}], "gust_n": -1.0},
            headers=srv.auth,
        )
        assert gusty.status_code == 422 and "gust_n" in gusty.text
        # twenty seconds cannot identify a vehicle: refused with the reason
        short = "\n".join(lines[:2001])
        refused = post(
            "/profiles/car/calibration",
            json={"base": {"params": BASE}, "recordings": [{"name": "short.csv", "csv": short}]},
            headers=srv.auth,
            timeout=120.0,
        )
        assert refused.status_code == 422 and "refused: too short" in refused.json()["detail"]
        # a body that is not a calibration request is the API's own 422
        assert post("/profiles/car/calibration", json={"recordings": []}, headers=srv.auth).status_code == 422
        # the service kept running and serving meanwhile
        assert srv.get("/health").status_code == 200
