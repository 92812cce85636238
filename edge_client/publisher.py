"""The 100 Hz publisher: many vehicles, one zenoh session, absolute-deadline pacing.

:class:`FleetPublisher` takes a :class:`~edge_client.sources.SampleSource` (a
simulated batch or a recording) and, at each tick k due at t_0 + k s:

1. steps the source and encodes one protocol Measurement per active vehicle,
   with sequence number k (bit FLAG_SEQUENCE_RESTART on k = 0) and timestamp
   t_wall,0 + k s (nanoseconds since the epoch: the sample's nominal time, so
   buffered samples keep theirs);
2. puts it, if a subscriber can receive it (the publisher's matching status),
   after flushing what was buffered for that vehicle; otherwise it appends it to
   the vehicle's bounded buffer (``buffer_s`` worth of samples). A full buffer
   drops its oldest sample, and that sample counts as **lost**: it was never sent;
3. puts the ground truth (GroundTruth JSON) of every vehicle once per 1/``truth_rate_hz`` s,
   a share of the vehicles at each tick.

A liveliness token per vehicle announces it. Estimates and alarms for the
publisher's vehicles come back on the protocol's keys; they give the round-trip
latency (publish time of seq -> receipt of its estimate), the per-vehicle
estimates and alarm events for the run's summary, and can be logged as JSON lines.

What this cannot count: samples put in the few milliseconds between a router's
death and zenoh noticing it leave without error and never arrive. The
estimates that come back (one per sample for a service that answers each one)
show those: compare ``estimates`` with ``sent``.
"""

from __future__ import annotations

import gc
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import TYPE_CHECKING, Literal, TextIO

import numpy as np

from agv_protocol.wire import (
    BINARY_ESTIMATE_KIND,
    DEFAULT_PREFIX,
    FLAG_SEQUENCE_RESTART,
    Alarm,
    Estimate,
    GroundTruth,
    Measurement,
    ProtocolError,
    decode_binary_estimate,
    fleet_selector,
    parse_vehicle_key,
)
from edge_client.pacing import DeadlinePacer, PacingStats
from edge_client.sources import SampleSource
from edge_client.stats import LatencyHistogram
from edge_client.transport import Received, Subscription, VehicleLinks, connected_nodes

if TYPE_CHECKING:
    import zenoh

#: Publish times are remembered for this many recent samples per vehicle (for the round trip).
LATENCY_RING = 4096
#: How often the wait for a subscriber before the first tick looks at the matching status [s].
LINK_POLL_S = 0.001
#: Alarm events kept per vehicle for the summary (later ones are only counted).
MAX_ALARM_EVENTS = 200
#: After a run's ``drain_s``, the wait for the last estimates goes on while an answered vehicle lacks some
#: (:func:`answered`) and they still arrive (one within DRAIN_QUIET_S), DRAIN_MAX_S at most in all [s]: a busy
#: machine's service may trail by more than the drain; one that decimates never answers every sample. The quiet
#: interval is a second: on a loaded 2-core machine a run's last estimates came over 0.25 s after the ones before
#: (the demo's summary, with 0.25 s, counted 18-38 of 40,000 estimates short, none lost).
DRAIN_QUIET_S = 1.0
DRAIN_MAX_S = 5.0
DRAIN_POLL_S = 0.01


@dataclass(frozen=True)
class PublisherOptions:
    """truth_rate_hz : ground-truth rate, 0 = off; buffer_s : per-vehicle buffer while undeliverable [s];
    warmup_s : estimates before this are left out of the 'quiet' peak (observer convergence) [s];
    gil_switch_interval_s : Python's thread switch interval during :meth:`FleetPublisher.run` (None = leave
    it). Estimates arrive on zenoh's threads; at the default 5 ms a receiving thread can hold the
    interpreter for up to 5 ms after the pacing loop's deadline. 0.5 ms bounds that wait.
    estimate_encoding : which of each vehicle's estimate keys to subscribe to: 'json' (``.../estimate``) or
    'binary' (``.../estimate.bin``, docs/protocol.md); the service makes only the encodings someone reads.
    link_wait_s : before the first tick, wait at most this long until a subscriber can receive every vehicle's
    measurements [s]. Zenoh learns the subscribers from the router a few milliseconds after the publishers are
    declared; until then the matching status says none, and a publisher without a buffer (a live bridge) would lose
    its first samples to that moment. After the wait the run starts whatever the status (a sample nobody can
    receive is then buffered or lost, as always)."""

    truth_rate_hz: float = 10.0
    buffer_s: float = 2.0
    warmup_s: float = 2.0
    prefix: str = DEFAULT_PREFIX
    gil_switch_interval_s: float | None = 0.0005
    estimate_encoding: Literal["json", "binary"] = "json"
    link_wait_s: float = 0.0

    def __post_init__(self) -> None:
        if self.estimate_encoding not in ("json", "binary"):
            raise ValueError(f"estimate_encoding must be 'json' or 'binary', got {self.estimate_encoding!r}")
        if not 0 <= self.truth_rate_hz <= 1000:
            raise ValueError(f"truth_rate_hz must be in [0, 1000], got {self.truth_rate_hz}")
        if not 0 <= self.buffer_s <= 600:
            raise ValueError(f"buffer_s must be in [0, 600], got {self.buffer_s}")
        if not 0 <= self.link_wait_s <= 600:
            raise ValueError(f"link_wait_s must be in [0, 600], got {self.link_wait_s}")
        if self.gil_switch_interval_s is not None and not 1e-5 <= self.gil_switch_interval_s <= 0.1:
            raise ValueError(f"gil_switch_interval_s must be in [1e-5, 0.1], got {self.gil_switch_interval_s}")


@dataclass(frozen=True)
class AlarmEvent:
    """An alarm message received back, with its receipt time on the publisher's monotonic clock."""

    received_ns: int
    alarm: Alarm


@dataclass
class VehicleRecord:
    """What the publisher knows of one vehicle. Peaks are max |estimate| of [T_f, delta_f]:
    ``quiet`` from warm-up to the fault onset (or the end), ``faulty`` from the onset on."""

    vehicle_id: str
    sent: int = 0
    lost: int = 0
    estimates: int = 0
    last_estimate: Estimate | None = None
    alarm_events: list[AlarmEvent] = field(default_factory=list)
    alarm_count: int = 0
    peak_quiet: np.ndarray = field(default_factory=lambda: np.zeros(2))
    peak_faulty: np.ndarray = field(default_factory=lambda: np.zeros(2))


def answered(records: Sequence[VehicleRecord]) -> bool:
    """Every vehicle the service answers has an estimate for each sample it sent. A vehicle without any estimate
    is not waited for (no service, or it does not serve that vehicle)."""
    return all(r.estimates >= r.sent for r in records if r.estimates > 0)


@dataclass(frozen=True)
class Progress:
    """A snapshot for the progress line; rates over the last interval."""

    elapsed_s: float
    ticks: int
    tick_rate_hz: float
    sample_rate_hz: float
    sent: int
    lost: int
    buffered: int
    late: int
    overruns: int
    rtt_p50_ms: float
    rtt_p99_ms: float
    estimates: int
    alarms: int
    linked: int
    vehicles: int
    connected: bool

    def line(self) -> str:
        """One line of at most 80 characters; the buffer is shown only when it holds samples."""
        if not self.connected:
            link = "DOWN"
        elif self.linked < self.vehicles:
            link = f"{self.linked}/{self.vehicles}"
        else:
            link = "up"
        elapsed = f"{self.elapsed_s:6.1f}s" if self.elapsed_s < 10_000 else f"{self.elapsed_s:.0f}s"
        buffered = f" buf {_count(self.buffered)}" if self.buffered else ""
        return (
            f"{elapsed} {self.tick_rate_hz:5.1f}Hz sent {_count(self.sent)} lost {_count(self.lost)}{buffered} "
            f"est {_count(self.estimates)} alarms {_count(self.alarms)} link {link} "
            f"rtt {_ms(self.rtt_p50_ms)}/{_ms(self.rtt_p99_ms)}ms"
        )[:80]


def _ms(value: float) -> str:
    if np.isnan(value):
        return "-"
    return f"{value:.1f}" if value < 10 else f"{value:.0f}"


def _count(n: int) -> str:
    """A count in at most 4 characters: 9999, 12k, 123k, 1.2M, 988M."""
    if n < 10_000:
        return str(n)
    for scale, suffix in ((1e3, "k"), (1e6, "M"), (1e9, "G")):
        value = n / scale
        if value < 9.95:
            return f"{value:.1f}{suffix}"
        if value < 999.5:
            return f"{value:.0f}{suffix}"
    return f"{n / 1e12:.0f}T"


@dataclass(frozen=True)
class PublishReport:
    """The end of a run: pacing, counts, round trip, and every vehicle's record.

    ``work_ms``: per-tick work, p50 and p99 of the source step ('source_*', the
    simulation) and of encoding + putting ('publish_*') [ms].
    """

    pacing: PacingStats
    sent: int
    lost: int
    unsent_at_end: int
    estimates: int
    alarms: int
    rtt_p50_ms: float
    rtt_p99_ms: float
    rtt_max_ms: float
    work_ms: dict[str, float]
    link_changes: int
    bad_messages: int
    start_ns: int
    end_ns: int
    period_ns: int
    vehicles: list[VehicleRecord]

    @property
    def elapsed_s(self) -> float:
        """From the first deadline to the end of the last tick's work [s]."""
        return (self.end_ns - self.start_ns) / 1e9

    @property
    def sample_rate_hz(self) -> float:
        """Samples produced per second per vehicle: (sent + lost + unsent) / vehicles / elapsed [Hz]."""
        if self.elapsed_s <= 0 or not self.vehicles:
            return 0.0
        return (self.sent + self.lost + self.unsent_at_end) / len(self.vehicles) / self.elapsed_s


class FleetPublisher:
    """Publish a source's vehicles at its sample rate through one session; collect what comes back.

    ``onset_s`` (per vehicle, None for a healthy one) splits the estimate peaks
    into quiet and faulty parts. ``log`` receives one JSON line per estimate and
    alarm received. Use as a context manager, or call :meth:`close`.
    """

    def __init__(
        self,
        session: zenoh.Session,
        source: SampleSource,
        options: PublisherOptions | None = None,
        *,
        onset_s: Sequence[float | None] | None = None,
        log: TextIO | None = None,
        clock: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        self.session = session
        self.source = source
        self.options = options or PublisherOptions()
        self.ids = list(source.vehicle_ids)
        nv = len(self.ids)
        period_s = source.sample_period_s
        self.period_ns = round(period_s * 1e9)
        self._clock = clock
        self.pacer = DeadlinePacer(period_s, clock=clock)
        self.records = [VehicleRecord(vehicle_id) for vehicle_id in self.ids]
        self._index = {vehicle_id: i for i, vehicle_id in enumerate(self.ids)}
        self._buffer_len = max(round(self.options.buffer_s / period_s), 0)
        self._buffers: list[deque[tuple[int, bytes]]] = [deque() for _ in range(nv)]
        # per vehicle, (seq, publish time) of recent samples in a ring: plain lists, cheap to write per put
        self._ring_seq = [[-1] * LATENCY_RING for _ in range(nv)]
        self._ring_ns = [[0] * LATENCY_RING for _ in range(nv)]
        onsets = onset_s if onset_s is not None else [None] * nv
        if len(onsets) != nv:
            raise ValueError(f"onset_s has {len(onsets)} entries for {nv} vehicles")
        never = np.iinfo(np.int64).max
        self._onset_seq = np.array([never if o is None else round(o / period_s) for o in onsets], dtype=np.int64)
        self._warmup_seq = round(self.options.warmup_s / period_s)
        self._truth_every = (
            0 if self.options.truth_rate_hz == 0 else max(round(1 / (self.options.truth_rate_hz * period_s)), 1)
        )
        self._work_ns = np.zeros((200_000, 2), dtype=np.int64)
        self.latency = LatencyHistogram()
        self._interval_latency = LatencyHistogram()
        self.estimates = 0
        self._last_estimate_ns = 0  # time.monotonic_ns of the latest estimate received
        self.alarms = 0
        self.bad_messages = 0
        self._log = log
        self._log_lock = threading.Lock()
        self._rx_lock = threading.Lock()
        self.start_wall_ns = 0
        self.links = VehicleLinks(session, self.ids, self.options.prefix, truth=self._truth_every > 0)
        self._put_measurement = self.links.measurement_putters()
        self._subscriptions: list[Subscription] = []
        try:
            kind = BINARY_ESTIMATE_KIND if self.options.estimate_encoding == "binary" else "estimate"
            self._subscriptions.append(
                Subscription(session, fleet_selector(kind, self.options.prefix), self._on_estimate)
            )
            self._subscriptions.append(
                Subscription(session, fleet_selector("alarm", self.options.prefix), self._on_alarm)
            )
        except BaseException:
            self.close()
            raise

    # -- receiving (zenoh threads) ------------------------------------------------------------

    def _vehicle_of(self, key: str) -> int | None:
        try:
            vehicle_id, _kind = parse_vehicle_key(key)
        except ProtocolError:
            return None
        return self._index.get(vehicle_id)

    def _on_estimate(self, rx: Received) -> None:
        i = self._vehicle_of(rx.key)
        if i is None:
            return
        binary = self.options.estimate_encoding == "binary"
        vehicle_id = self.ids[i]
        estimate = rx.decode(partial(decode_binary_estimate, vehicle_id=vehicle_id) if binary else Estimate.decode)
        if estimate is None:
            self.bad_messages += 1
            return
        slot = estimate.seq % LATENCY_RING
        with self._rx_lock:
            if self._ring_seq[i][slot] == estimate.seq:
                rtt = rx.received_ns - self._ring_ns[i][slot]
                self.latency.add(rtt)
                self._interval_latency.add(rtt)
            record = self.records[i]
            record.estimates += 1
            self.estimates += 1
            self._last_estimate_ns = rx.received_ns
            record.last_estimate = estimate
            if estimate.seq >= self._warmup_seq:
                peaks = record.peak_faulty if estimate.seq >= self._onset_seq[i] else record.peak_quiet
                peaks[0] = max(peaks[0], abs(estimate.torque_fault))
                peaks[1] = max(peaks[1], abs(estimate.steer_fault))
        self._write_log("estimate", rx, estimate.model_dump_json() if binary else None)

    def _on_alarm(self, rx: Received) -> None:
        i = self._vehicle_of(rx.key)
        if i is None:
            return
        alarm = rx.decode(Alarm.decode)
        if alarm is None:
            self.bad_messages += 1
            return
        with self._rx_lock:
            record = self.records[i]
            record.alarm_count += 1
            self.alarms += 1
            if len(record.alarm_events) < MAX_ALARM_EVENTS:
                record.alarm_events.append(AlarmEvent(rx.received_ns, alarm))
        self._write_log("alarm", rx)

    def _write_log(self, kind: str, rx: Received, document: str | None = None) -> None:
        """One JSON line: the message as received, or ``document`` (a binary estimate as its JSON document)."""
        if self._log is None:
            return
        message = rx.payload.decode() if document is None else document
        line = f'{{"type":"{kind}","received_unix_ns":{time.time_ns()},"message":{message}}}\n'
        with self._log_lock:
            self._log.write(line)

    # -- publishing (caller's thread) ---------------------------------------------------------

    def deadline_ns(self, k: int) -> int:
        """When sample k was due, on the publisher's monotonic clock [ns]."""
        return self.pacer.deadline_ns(k)

    def _put(self, i: int, seq: int, payload: bytes) -> None:
        slot = seq % LATENCY_RING
        self._ring_seq[i][slot] = seq
        self._ring_ns[i][slot] = self._clock()
        self._put_measurement[i](payload)
        self.records[i].sent += 1

    def _publish_tick(self) -> None:
        started = self._clock()
        tick = self.source.next_tick()
        stepped = self._clock()
        k = tick.k
        timestamp_ns = self.start_wall_ns + k * self.period_ns
        flags = FLAG_SEQUENCE_RESTART if k == 0 else 0
        y = tick.y.tolist()
        u = tick.u.tolist()
        active = tick.active.tolist()
        grade = None if tick.grade is None else tick.grade.tolist()
        matched = self.links.matched.tolist()  # a snapshot: zenoh threads may change it meanwhile
        for i, vehicle_id in enumerate(self.ids):
            if not active[i]:
                continue
            g_i = None if grade is None or grade[i] != grade[i] else grade[i]  # NaN: this vehicle reports none
            payload = Measurement(vehicle_id, k, timestamp_ns, y[i][0], y[i][1], u[i][0], u[i][1], flags, g_i).encode()
            buffer = self._buffers[i]
            if matched[i]:
                while buffer:
                    seq, old = buffer.popleft()
                    self._put(i, seq, old)
                self._put(i, k, payload)
            elif self._buffer_len > 0:
                if len(buffer) >= self._buffer_len:
                    buffer.popleft()
                    self.records[i].lost += 1
                buffer.append((k, payload))
            else:
                self.records[i].lost += 1
        if self._truth_every and tick.x is not None and tick.f is not None:
            # vehicle i's truth goes out when (k + i) % every == 0: each vehicle at the truth rate,
            # the work spread evenly over the ticks instead of all of it every 10th tick
            x = tick.x
            f = tick.f
            for i in range((-k) % self._truth_every, len(self.ids), self._truth_every):
                if active[i]:
                    truth = GroundTruth(
                        vehicle=self.ids[i],
                        seq=k,
                        t_ns=timestamp_ns,
                        vx=float(x[i, 0]),
                        vy=float(x[i, 1]),
                        r=float(x[i, 2]),
                        torque_fault=float(f[i, 0]),
                        steer_fault=float(f[i, 1]),
                    )
                    self.links.put_truth(i, truth.encode())
        slot = (self.pacer.ticks - 1) % self._work_ns.shape[0]
        self._work_ns[slot] = (stepped - started, self._clock() - stepped)

    def _work_stats(self) -> dict[str, float]:
        work = self._work_ns[: min(self.pacer.ticks, self._work_ns.shape[0])] / 1e6
        if work.size == 0:
            return {}
        return {
            f"{part}_{name}": float(np.percentile(work[:, column], q))
            for column, part in enumerate(("source", "publish"))
            for name, q in (("p50", 50), ("p99", 99))
        }

    def _totals(self) -> tuple[int, int, int]:
        sent = sum(r.sent for r in self.records)
        lost = sum(r.lost for r in self.records)
        buffered = sum(len(b) for b in self._buffers)
        return sent, lost, buffered

    def _progress(self, previous: tuple[int, int, int]) -> Progress:
        ticks_before, sent_before, now_before = previous
        now = self._clock()
        sent, lost, buffered = self._totals()
        interval_s = max((now - now_before) / 1e9, 1e-9)
        with self._rx_lock:
            interval, self._interval_latency = self._interval_latency, LatencyHistogram()
        stats = self.pacer
        return Progress(
            elapsed_s=(now - (stats.start_ns or now)) / 1e9,
            ticks=stats.ticks,
            tick_rate_hz=(stats.ticks - ticks_before) / interval_s,
            sample_rate_hz=(sent - sent_before) / interval_s,
            sent=sent,
            lost=lost,
            buffered=buffered,
            late=stats.late,
            overruns=stats.overruns,
            rtt_p50_ms=interval.quantile_ms(0.5),
            rtt_p99_ms=interval.quantile_ms(0.99),
            estimates=self.estimates,
            alarms=self.alarms,
            linked=int(self.links.matched.sum()),
            vehicles=len(self.ids),
            connected=connected_nodes(self.session) > 0,
        )

    def run(
        self,
        duration_s: float | None = None,
        *,
        stop: threading.Event | None = None,
        on_progress: Callable[[Progress], None] | None = None,
        progress_period_s: float = 1.0,
        drain_s: float = 0.5,
    ) -> PublishReport:
        """Publish until ``duration_s`` of samples (or the source's end), or ``stop`` is set.

        Then flush what is buffered if it can be delivered, wait ``drain_s`` for the last
        estimates, longer while they still arrive for samples not yet answered (DRAIN_MAX_S
        at most; none for ``drain_s`` 0), and return the report. Buffered samples still undeliverable
        at the end are counted in ``unsent_at_end``.
        """
        n_ticks = self.source.n_samples
        if duration_s is not None:
            n_ticks = min(n_ticks, round(duration_s / self.source.sample_period_s))
        previous_switch = sys.getswitchinterval()
        if self.options.gil_switch_interval_s is not None:
            sys.setswitchinterval(self.options.gil_switch_interval_s)
        # everything built so far (scenarios, compiled signals, zenoh objects) is long-lived: keep it out
        # of the collector's full passes, which otherwise stall a big fleet's loop for tens of ms
        gc.freeze()
        try:
            return self._run(n_ticks, stop, on_progress, progress_period_s, drain_s)
        finally:
            gc.unfreeze()
            sys.setswitchinterval(previous_switch)

    def _drain(self, drain_s: float) -> None:
        """Wait ``drain_s`` [s], then while an answered vehicle still lacks estimates and they still arrive."""
        if drain_s <= 0:
            return
        deadline = time.monotonic_ns() + round(max(drain_s, DRAIN_MAX_S) * 1e9)
        time.sleep(drain_s)
        while True:
            now = time.monotonic_ns()
            with self._rx_lock:
                done, last = answered(self.records), self._last_estimate_ns
            if done or now >= deadline or now - last > DRAIN_QUIET_S * 1e9:
                return
            time.sleep(DRAIN_POLL_S)

    def _run(
        self,
        n_ticks: int,
        stop: threading.Event | None,
        on_progress: Callable[[Progress], None] | None,
        progress_period_s: float,
        drain_s: float,
    ) -> PublishReport:
        progress_ns = round(progress_period_s * 1e9)
        self._wait_for_link()
        self.source.prepare()
        self.start_wall_ns = time.time_ns()
        start = self.pacer.start()
        next_progress = start + progress_ns
        previous = (0, 0, start)
        for _ in range(n_ticks):
            if stop is not None and stop.is_set():
                break
            self.pacer.wait()
            self._publish_tick()
            if on_progress is not None and self.pacer.last_tick_ns >= next_progress:
                progress = self._progress(previous)
                previous = (progress.ticks, progress.sent, self._clock())
                next_progress += progress_ns
                on_progress(progress)
        end_ns = self._clock()
        pacing = self.pacer.stats()
        for i, buffer in enumerate(self._buffers):
            if buffer and self.links.matched[i]:
                while buffer:
                    seq, payload = buffer.popleft()
                    self._put(i, seq, payload)
        self._drain(drain_s)
        sent, lost, unsent = self._totals()
        with self._rx_lock:
            vehicles = list(self.records)
        return PublishReport(
            pacing=pacing,
            sent=sent,
            lost=lost,
            unsent_at_end=unsent,
            estimates=self.estimates,
            alarms=self.alarms,
            rtt_p50_ms=self.latency.quantile_ms(0.5),
            rtt_p99_ms=self.latency.quantile_ms(0.99),
            rtt_max_ms=self.latency.max_ns / 1e6,
            work_ms=self._work_stats(),
            link_changes=self.links.match_changes,
            bad_messages=self.bad_messages,
            start_ns=self.pacer.start_ns or 0,
            end_ns=end_ns,
            period_ns=self.period_ns,
            vehicles=vehicles,
        )

    def _wait_for_link(self) -> None:
        """Wait at most ``options.link_wait_s`` until some subscriber can receive every vehicle's measurements."""
        deadline = time.monotonic() + self.options.link_wait_s
        while not self.links.matched.all() and time.monotonic() < deadline:
            time.sleep(LINK_POLL_S)

    def close(self) -> None:
        """Undeclare subscriptions, publishers and tokens (the session stays open: its owner closes it)."""
        for subscription in self._subscriptions:
            subscription.close()
        self._subscriptions.clear()
        self.links.close()

    def __enter__(self) -> FleetPublisher:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()
