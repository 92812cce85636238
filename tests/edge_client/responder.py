"""TEST-ONLY stand-in for the cloud service, until the real one (branch `service`) is merged.

It speaks the wire protocol for real over zenoh: subscribes to every vehicle's
measurements, runs the real certified observer (synth.observer, batched over
the vehicles it has seen), publishes one Estimate per measurement and raises or
clears Alarms with the thresholds edge_client.fleet_mix assumes of the service
(|T_f| > 40 N m or |delta_f| > 0.01 rad for 0.5 s, after a 1 s warm-up). After
a gap in a vehicle's sequence numbers its observer restarts and warms up again.
It is
a fixture, not product code: no storage, no REST, no gain management.
"""

from __future__ import annotations

import threading
from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np

from edge_client.fleet_mix import ASSUMED_ALARM, AlarmAssumption
from edge_client.transport import ChannelSubscription, TransportOptions, open_session
from service.protocol import (
    FLAG_SEQUENCE_RESTART,
    Alarm,
    Estimate,
    Measurement,
    ProtocolError,
    fleet_selector,
    vehicle_key,
)
from synth.gains import ObserverGains
from synth.observer import RuntimeGains, initial_observer_state, observer_step

WARMUP_SAMPLES = 100
CHANNELS = ("torque_fault", "steer_fault")


@dataclass
class _Vehicle:
    index: int
    samples: int = 0
    last_seq: int = -1
    gaps: int = 0
    seqs: list[int] = field(default_factory=list)
    above: np.ndarray = field(default_factory=lambda: np.zeros(2, dtype=int))
    below: np.ndarray = field(default_factory=lambda: np.zeros(2, dtype=int))
    raised: np.ndarray = field(default_factory=lambda: np.zeros(2, dtype=bool))
    alarm_serial: int = 0


class ResponderService:
    """Measurements in, estimates and alarms out, on its own zenoh session and thread."""

    #: One Estimate per Measurement, so a test may count missing estimates as missing samples.
    answers_every_sample = True

    def __init__(
        self,
        transport: TransportOptions,
        gains: ObserverGains,
        alarm: AlarmAssumption = ASSUMED_ALARM,
    ) -> None:
        self.runtime = RuntimeGains.from_gains(gains)
        self.gains_version = gains.version
        self.prefix = transport.prefix
        self.thresholds = np.array([alarm.torque_threshold_nm, alarm.steer_threshold_rad])
        self.persistence = round(alarm.persistence_s / gains.params.sample_period_s)
        self.vehicles: dict[str, _Vehicle] = {}
        self.z = np.zeros((0, self.runtime.n))
        self.bad_messages = 0
        self.alarms_sent: dict[str, list[Alarm]] = defaultdict(list)
        self._publishers: dict[tuple[str, str], object] = {}
        self.session = open_session(transport)
        self._subscription = ChannelSubscription(self.session, fleet_selector("meas", self.prefix), 200_000)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="responder", daemon=True)
        self._thread.start()

    def received(self, vehicle_id: str) -> list[int]:
        """Sequence numbers received for a vehicle, in arrival order."""
        vehicle = self.vehicles.get(vehicle_id)
        return list(vehicle.seqs) if vehicle else []

    def _loop(self) -> None:
        while not self._stop.wait(0.002):
            batch = self._subscription.drain()
            if batch:
                self._process([rx.payload for rx in batch])

    def _vehicle(self, vehicle_id: str) -> _Vehicle:
        vehicle = self.vehicles.get(vehicle_id)
        if vehicle is None:
            vehicle = _Vehicle(index=len(self.vehicles))
            self.vehicles[vehicle_id] = vehicle
            self.z = np.vstack([self.z, np.zeros((1, self.runtime.n))])
        return vehicle

    def _process(self, payloads: list[bytes]) -> None:
        by_vehicle: dict[str, list[Measurement]] = defaultdict(list)
        for payload in payloads:
            try:
                m = Measurement.decode(payload)
            except ProtocolError:
                self.bad_messages += 1
                continue
            by_vehicle[m.vehicle_id].append(m)
        # one batched observer step per round: round j takes the j-th new sample of every vehicle
        rounds = max((len(v) for v in by_vehicle.values()), default=0)
        for j in range(rounds):
            batch = [(vid, ms[j]) for vid, ms in by_vehicle.items() if j < len(ms)]
            vehicles = [self._vehicle(vid) for vid, _ in batch]
            index = np.array([v.index for v in vehicles])
            y = np.array([[m.vx_mps, m.r_radps] for _, m in batch])
            u = np.array([[m.torque_nm, m.steer_rad] for _, m in batch])
            for row, (vehicle, (_, m)) in enumerate(zip(vehicles, batch, strict=True)):
                # a new stream, or a gap in the sequence: the observer restarts from this measurement
                # (stepping over missing samples would feed it a jump) and warms up again
                gap = vehicle.samples > 0 and m.seq != vehicle.last_seq + 1
                vehicle.gaps += gap
                if vehicle.samples == 0 or gap or m.flags & FLAG_SEQUENCE_RESTART:
                    self.z[vehicle.index] = initial_observer_state(self.runtime, y[row : row + 1])[0]
                    vehicle.samples = 0
                vehicle.last_seq = m.seq
            z_next, result = observer_step(self.runtime, self.z[index], y, u)
            self.z[index] = z_next
            for row, (vehicle, (vid, m)) in enumerate(zip(vehicles, batch, strict=True)):
                vehicle.samples += 1
                vehicle.seqs.append(m.seq)
                x_hat = result.x_hat[row]
                level = self._alarms(vid, vehicle, x_hat[3:5], m)
                estimate = Estimate(
                    vehicle=vid,
                    seq=m.seq,
                    t_ns=m.timestamp_ns,
                    vx=float(x_hat[0]),
                    vy=float(x_hat[1]),
                    r=float(x_hat[2]),
                    torque_fault=float(x_hat[3]),
                    steer_fault=float(x_hat[4]),
                    in_domain=bool(result.in_domain[row]),
                    gain_version=self.gains_version,
                    level=level,
                )
                self._put(vid, "estimate", estimate.encode())

    def _alarms(self, vehicle_id: str, vehicle: _Vehicle, faults: np.ndarray, m: Measurement) -> str:
        if vehicle.samples < WARMUP_SAMPLES:
            return "OK"
        above = np.abs(faults) > self.thresholds
        vehicle.above = np.where(above, vehicle.above + 1, 0)
        vehicle.below = np.where(above, 0, vehicle.below + 1)
        for ch in range(2):
            change = None
            if not vehicle.raised[ch] and vehicle.above[ch] >= self.persistence:
                change = "raised"
            elif vehicle.raised[ch] and vehicle.below[ch] >= self.persistence:
                change = "cleared"
            if change is None:
                continue
            vehicle.raised[ch] = change == "raised"
            if change == "raised":
                vehicle.alarm_serial += 1
            alarm = Alarm(
                vehicle=vehicle_id,
                id=f"{vehicle_id}-{CHANNELS[ch]}-{vehicle.alarm_serial}",
                kind=CHANNELS[ch],
                level="FAULT",
                state=change,
                value=float(faults[ch]),
                threshold=float(self.thresholds[ch]),
                t_ns=m.timestamp_ns,
            )
            self.alarms_sent[vehicle_id].append(alarm)
            self._put(vehicle_id, "alarm", alarm.encode())
        return "FAULT" if vehicle.raised.any() else "OK"

    def _put(self, vehicle_id: str, kind: str, payload: bytes) -> None:
        key = vehicle_key(vehicle_id, kind, self.prefix)
        publisher = self._publishers.get((vehicle_id, kind))
        if publisher is None:
            publisher = self.session.declare_publisher(key)
            self._publishers[(vehicle_id, kind)] = publisher
        publisher.put(payload)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self._subscription.close()
        for publisher in self._publishers.values():
            publisher.undeclare()
        self.session.close()
