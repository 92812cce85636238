"""The loss-of-effectiveness stage in the service: a profile that enables it gets estimates carrying the biases
and effectiveness over Zenoh and REST, equal to the offline stage on the same measurements, alarms on alpha, and
the stage switched off again by a profile change without a new design.

A real service (uvicorn, Zenoh on loopback, SQLite); assertions on values and order, never on speed.
"""

from __future__ import annotations

import numpy as np
import pytest
import zenoh

from agv_protocol.wire import EFFECTIVENESS_COLUMNS, FleetEstimates, fleet_estimates_selector
from synth.effectiveness import EffectivenessObserver
from synth.gains import ObserverGains
from tests.service.helpers import make_settings, plant_measurements, probe, running, wait_for
from tests.synth.test_effectiveness import ALPHA_MIN, OPTIONS, RAMP_END_S, torque_loss_scenario
from tests.tolerances import BATCH_EQUALITY_ATOL, STAGE_BATCH_ATOL

pytestmark = pytest.mark.network

SAMPLES = 2600  # 26 s: the ramp ends at 18 s, alpha is read 2 s later
STAGE = OPTIONS.model_dump(mode="json")
PROFILE = {
    "design": {"design": "robust"},
    "effectiveness": STAGE,
    # only alpha should raise an alarm here (and no STALE when this busy machine pauses the sender)
    "alarms": {"torque_warn_nm": 1000.0, "torque_fault_nm": 2000.0, "stale_after_s": 600.0},
}


def test_the_service_runs_the_effectiveness_stage_and_alarms_on_alpha(tmp_path):
    settings = make_settings(tmp_path, {"loe": PROFILE}, ingest={"default_profile": "loe"})
    samples = plant_measurements(["loe-1"], SAMPLES, scenario=torque_loss_scenario())
    with running(settings) as srv, probe(settings.zenoh.endpoint) as p:
        fleet = p.session.declare_subscriber(fleet_estimates_selector(), zenoh.handlers.FifoChannel(1 << 16))
        try:
            for row in samples:
                p.put(row[0])
            wait_for(lambda: len(p.estimates_of("loe-1")) >= SAMPLES, what="every estimate")
            got = p.estimates_of("loe-1")
            groups = [FleetEstimates.decode(s.payload.to_bytes()).groups for s in iter(fleet.try_recv, None)]
        finally:
            fleet.undeclare()
        assert [e.seq for e in got] == list(range(SAMPLES))
        # the offline stage on the same measurements with the gains the service ran
        gains = ObserverGains.from_dict(srv.get("/profiles/loe/gains", params={"matrices": "true"}).json())
        y = np.array([[m.vx_mps, m.r_radps] for (m,) in samples])
        u = np.array([[m.torque_nm, m.steer_rad] for (m,) in samples])
        offline = EffectivenessObserver(gains, OPTIONS, y[:1], None, u[:1])
        expected = [offline.step(y[k : k + 1], u[k : k + 1]) for k in range(SAMPLES)]
        alpha = np.array([[e.torque_alpha, e.steer_alpha] for e in got], dtype=float)
        np.testing.assert_allclose(alpha, np.vstack([s.alpha for s in expected]), atol=BATCH_EQUALITY_ATOL)
        bias = np.array([[e.torque_bias, e.steer_bias] for e in got], dtype=float)
        np.testing.assert_allclose(bias, np.vstack([s.bias for s in expected]), atol=STAGE_BATCH_ATOL)
        total = np.array([[e.torque_fault, e.steer_fault] for e in got])
        np.testing.assert_allclose(total, np.vstack([s.faults for s in expected]), atol=STAGE_BATCH_ATOL)
        # the effectiveness recovered within 3 % two seconds after the ramp ends, steering untouched
        at = round((RAMP_END_S + 2.0) * 100)
        assert abs(got[at].torque_alpha - ALPHA_MIN) <= 0.03 * ALPHA_MIN  # type: ignore[operator]
        assert abs(got[at].steer_alpha - 1.0) <= 0.03  # type: ignore[operator]
        # alpha below 0.75 held 1 s: a torque_effectiveness FAULT on Zenoh, none on steering or torque totals
        alarms = p.collect().alarms
        kinds = {(a.kind, a.level) for a in alarms if a.state == "raised"}
        assert ("torque_effectiveness", "FAULT") in kinds, kinds
        assert not {k for k, _ in kinds} - {"torque_effectiveness"}, kinds
        fault = next(a for a in alarms if a.kind == "torque_effectiveness" and a.level == "FAULT")
        assert fault.threshold == 0.75 and fault.value is not None and fault.value < 0.75
        assert got[-1].level == "FAULT"
        # the fleet stream carries the stage's columns too
        columns = {name for g in groups for group in g for name in EFFECTIVENESS_COLUMNS if getattr(group, name)}
        assert columns == set(EFFECTIVENESS_COLUMNS)
        # REST: the latest estimate and the history rows carry them
        latest = srv.vehicle("loe-1")["latest_estimate"]
        assert latest["seq"] == SAMPLES - 1 and latest["torque_alpha"] == pytest.approx(got[-1].torque_alpha)
        history = srv.get("/vehicles/loe-1/estimates", params={"limit": 3}).json()["estimates"]
        assert [h["torque_alpha"] for h in history] == pytest.approx([e.torque_alpha for e in got[-3:]])
        # switched off by a profile change: applied at once (no design job), later estimates without the columns
        off = {**PROFILE, "effectiveness": {**STAGE, "enabled": False}}
        r = srv.http.put("/profiles/loe", json=off, headers=srv.auth)
        assert r.status_code == 200, r.text
        more = plant_measurements(["loe-1"], 20, seq0=SAMPLES, scenario=torque_loss_scenario())
        for (m,) in more:
            p.put(m)
        wait_for(lambda: len(p.estimates_of("loe-1")) >= SAMPLES + 20, what="estimates after the change")
        after = p.estimates_of("loe-1")[SAMPLES:]
        assert all(e.torque_alpha is None and e.torque_bias is None for e in after)
        assert "torque_alpha" not in srv.vehicle("loe-1")["latest_estimate"] or (
            srv.vehicle("loe-1")["latest_estimate"]["torque_alpha"] is None
        )
