"""SIGKILL during a synthesis job: after the restart the job is reported interrupted and its design resumed."""

from __future__ import annotations

import pytest

from tests.service.helpers import FAST_DESIGN, job_done, make_settings, running, service_process, wait_for

pytestmark = pytest.mark.network


def test_a_design_accepted_before_a_crash_is_resumed_after_the_restart(tmp_path):
    """202 means the design will happen: a SIGKILL during it leaves the job interrupted, and the restarted
    service designs the same request again (a new job that says which one it resumes)."""
    settings = make_settings(tmp_path, {"default": {"design": FAST_DESIGN}})
    with service_process(settings, tmp_path / "service.log") as srv:
        srv.wait_ready()
        before = srv.get("/profiles/default").json()["active_version"]
        accepted = srv.http.put(
            "/profiles/default", json={"design": {**FAST_DESIGN, "fault_order": 2}}, headers=srv.auth
        )
        assert accepted.status_code == 202
        srv.kill()  # the worker needs seconds to start and solve: the job is queued or running now
    with running(settings) as again:
        first = again.get(f"/jobs/{accepted.json()['job']}").json()
        assert first["status"] == "interrupted" and first["error"] == "restart"
        resumed = wait_for(
            lambda: [j for j in again.get("/jobs").json() if j.get("resumes") == first["id"]], what="the resumed job"
        )[0]
        done = wait_for(lambda: job_done(again, resumed["id"]), what="the resumed design")
        assert done["status"] == "succeeded" and done["spec"] == first["spec"]
        profile = again.get("/profiles/default").json()
        assert profile["active_version"] == done["gain_version"] != before
        assert profile["spec"]["design"]["fault_order"] == 2
