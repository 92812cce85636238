"""A simulated fleet against the service: build the fleet, publish it, summarise what came back.

The engine of `agv-fe fleet`. The summary says, per vehicle, what was injected,
what the service estimated (peak |estimate| before and after the fault onset),
whether it raised a fault alarm and how long after the onset the alarm arrived.
A fault alarm on a healthy vehicle, or before a faulty vehicle's onset, is a
false alarm.
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
import threading
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np
from rich.console import Console
from rich.table import Table

from edge_client.faults import BiasFault, Fault, LossOfEffectivenessFault, SinusoidalFault
from edge_client.fleet_mix import DEFAULT_MIX, FleetMember, build_fleet
from edge_client.publisher import FleetPublisher, Progress, PublisherOptions, PublishReport
from edge_client.scenario import Scenario, SensorNoise
from edge_client.sources import SimulatedSource, Tick
from edge_client.transport import TransportOptions, close_session, open_session, report_payload
from synth.model import FloatArray

#: Alarm kinds that say "this actuator is faulty"; others (stale, out_of_domain...) are reported apart.
FAULT_ALARM_KINDS = frozenset({"torque_fault", "steer_fault"})


@dataclass(frozen=True)
class FleetConfig:
    """Everything `agv-fe fleet` needs."""

    n_vehicles: int = 10
    duration_s: float = 60.0
    mix: str = DEFAULT_MIX
    seed: int = 0
    noise: SensorNoise | None = None
    gusts: bool = False
    loads: bool = False
    hills: bool = False
    id_prefix: str = "veh"
    transport: TransportOptions = field(default_factory=TransportOptions)
    publisher: PublisherOptions = field(default_factory=PublisherOptions)
    log_path: Path | None = None

    def members(self) -> list[FleetMember]:
        """The fleet of this configuration: ``n_vehicles`` drawn from ``mix`` with ``seed``.

        Raises
        ------
        MixError, ScenarioError, ValueError
            The mix is not one (its text, a scenario, a share).
        """
        return build_fleet(
            self.mix,
            self.n_vehicles,
            self.duration_s,
            seed=self.seed,
            noise=self.noise,
            id_prefix=self.id_prefix,
            gusts=self.gusts,
            loads=self.loads,
            hills=self.hills,
        )


class TruthTracker:
    """A source wrapper that remembers each vehicle's peak |true fault| (nv, 2)."""

    def __init__(self, source: SimulatedSource) -> None:
        self.source = source
        self.peak = np.zeros((len(source.vehicle_ids), 2))

    @property
    def vehicle_ids(self) -> list[str]:
        return self.source.vehicle_ids

    @property
    def sample_period_s(self) -> float:
        return self.source.sample_period_s

    @property
    def n_samples(self) -> int:
        return self.source.n_samples

    def prepare(self) -> None:
        self.source.prepare()

    def next_tick(self) -> Tick:
        tick = self.source.next_tick()
        if tick.f is not None:
            np.maximum(self.peak, np.abs(tick.f), out=self.peak)
        return tick


def describe_fault(fault: Fault) -> str:
    """A short description: 'T_f bias +111.5 N m @5.2s', 'δ_f sine 0.02 rad 0.8 rad/s @3.5s'."""
    symbol, unit = ("T_f", "N m") if fault.channel == "torque" else ("δ_f", "rad")
    if isinstance(fault, BiasFault):
        text = f"{symbol} bias {fault.magnitude:+g} {unit}"
    elif isinstance(fault, LossOfEffectivenessFault):
        text = f"{symbol} LoE to {fault.alpha_min:g} at {fault.rate_per_s:g}/s"
    elif isinstance(fault, SinusoidalFault):
        text = f"{symbol} sine {fault.amplitude:g} {unit} {fault.omega_radps:.2g} rad/s"
    else:
        text = f"{symbol} intermittent {fault.magnitude:+g} {unit} {fault.on_s:.2g}/{fault.period_s:.2g}s"
    return f"{text} @{fault.onset_s:.3g}s"


def describe_conditions(scenario: Scenario) -> str:
    """What the vehicle carries and where it drives, as it reports them: '120 kg, hills +-4.6 %', or ''."""
    parts = []
    if scenario.payload_kg > 0.0:
        parts.append(f"{scenario.payload_kg:g} kg")
    if scenario.road_grade is not None:
        steepest = abs(scenario.road_grade.offset_rad) + scenario.road_grade.amplitude_rad
        parts.append(f"hills ±{100 * math.tan(steepest):.1f} %")
    return ", ".join(parts)


@dataclass(frozen=True)
class VehicleSummary:
    """One vehicle's outcome. Peaks are [T_f [N m], delta_f [rad]]; delays in [s]."""

    vehicle_id: str
    kind: str
    injected: str
    onset_s: float | None
    true_peak: tuple[float, float]
    estimated_peak_quiet: tuple[float, float]
    estimated_peak_faulty: tuple[float, float]
    sent: int
    lost: int
    estimates: int
    last_estimate_seq: int | None
    fault_alarms: tuple[str, ...]
    first_alarm_after_onset_s: float | None
    false_alarms: int
    other_alarms: tuple[str, ...]
    #: the run reached the fault's onset (a run stopped early may end before a fault begins)
    fault_started: bool = True
    #: its payload and road, as it reported them (:func:`describe_conditions`; '' empty on level ground)
    conditions: str = ""

    @property
    def faulty(self) -> bool:
        """A fault was injected and had begun before the run ended."""
        return self.onset_s is not None and self.fault_started

    @property
    def detected(self) -> bool:
        return self.first_alarm_after_onset_s is not None


@dataclass(frozen=True)
class FleetSummary:
    """The fleet run's report and its per-vehicle outcomes."""

    report: PublishReport
    vehicles: list[VehicleSummary]
    #: loaded vehicles whose payload report reached the service before their first sample
    payloads_reported: int = 0

    @property
    def false_alarms(self) -> int:
        return sum(v.false_alarms for v in self.vehicles)

    def to_dict(self) -> dict[str, object]:
        p = self.report.pacing
        return {
            "pacing": asdict(p),
            "elapsed_s": self.report.elapsed_s,
            "sample_rate_hz": self.report.sample_rate_hz,
            "sent": self.report.sent,
            "lost": self.report.lost,
            "unsent_at_end": self.report.unsent_at_end,
            "estimates": self.report.estimates,
            "alarms": self.report.alarms,
            "rtt_ms": {"p50": self.report.rtt_p50_ms, "p99": self.report.rtt_p99_ms, "max": self.report.rtt_max_ms},
            "link_changes": self.report.link_changes,
            "false_alarms": self.false_alarms,
            "payloads_reported": self.payloads_reported,
            "vehicles": [asdict(v) for v in self.vehicles],
        }

    def totals_line(self) -> str:
        r = self.report
        faulty = [v for v in self.vehicles if v.faulty]
        detected = sum(v.detected for v in faulty)
        loaded = sum(" kg" in v.conditions for v in self.vehicles)
        payloads = f"payloads reported {self.payloads_reported}/{loaded}; " if loaded else ""
        return (
            f"{len(self.vehicles)} vehicles, {r.elapsed_s:.1f} s at {r.sample_rate_hz:.2f} Hz "
            f"(late ticks {r.pacing.late}, overruns {r.pacing.overruns}); sent {r.sent}, lost {r.lost}, "
            f"unsent at end {r.unsent_at_end}; estimates {r.estimates}; round trip p50 {r.rtt_p50_ms:.2f} ms, "
            f"p99 {r.rtt_p99_ms:.2f} ms; {payloads}faulty vehicles alarmed {detected}/{len(faulty)}; "
            f"false alarms {self.false_alarms}"
        )

    def table(self) -> Table:
        """The per-vehicle table, readable at 80 columns."""
        table = Table(title="fleet summary", expand=False, pad_edge=False, show_edge=False)
        table.add_column("vehicle", no_wrap=True)
        table.add_column("injected")
        table.add_column("est. peak\nT_f / δ_f", justify="right", no_wrap=True)
        table.add_column("quiet peak\nT_f / δ_f", justify="right", no_wrap=True)
        table.add_column("alarm", no_wrap=True)
        table.add_column("after", justify="right", no_wrap=True)
        for v in self.vehicles:
            faulty_peak = f"{v.estimated_peak_faulty[0]:.1f} / {v.estimated_peak_faulty[1]:.3f}" if v.faulty else "-"
            quiet_peak = f"{v.estimated_peak_quiet[0]:.1f} / {v.estimated_peak_quiet[1]:.3f}"
            alarm = ",".join(k.removesuffix("_fault") for k in v.fault_alarms) or "none"
            if v.false_alarms:
                alarm = f"[red]{alarm} FALSE[/red]"
            after = f"{v.first_alarm_after_onset_s:.2f}s" if v.first_alarm_after_onset_s is not None else "-"
            injected = f"{v.injected}\n{v.conditions}" if v.conditions else v.injected
            table.add_row(v.vehicle_id, injected, faulty_peak, quiet_peak, alarm, after)
        return table

    def render_text(self, width: int = 80) -> str:
        console = Console(width=width, record=True, file=io.StringIO(), color_system=None)
        console.print(self.table())
        console.print(self.totals_line())
        return console.export_text()


def summarize(
    members: Sequence[FleetMember], report: PublishReport, true_peak: FloatArray, deadline_ns: Callable[[int], int]
) -> FleetSummary:
    """Per-vehicle outcomes from the publisher's report and the injected faults."""
    period_s = report.period_ns / 1e9
    vehicles = []
    for member, record, peak in zip(members, report.vehicles, true_peak, strict=True):
        onset = member.fault_onset_s
        onset_ns = deadline_ns(round(onset / period_s)) if onset is not None else None
        raised = [e for e in record.alarm_events if e.alarm.state == "raised"]
        fault_raised = [e for e in raised if e.alarm.kind in FAULT_ALARM_KINDS]
        false_alarms = sum(1 for e in fault_raised if onset_ns is None or e.received_ns < onset_ns)
        after_onset = [e for e in fault_raised if onset_ns is not None and e.received_ns >= onset_ns]
        first = min((e.received_ns for e in after_onset), default=None)
        injected = "; ".join(describe_fault(f) for f in member.scenario.faults) or "healthy"
        ran_s = (record.sent + record.lost) * period_s  # vehicle time the run covered, sent or not
        started = onset is None or onset < ran_s
        if not started:
            injected += f" (not begun: the run ended at {ran_s:.1f} s)"
        vehicles.append(
            VehicleSummary(
                vehicle_id=member.vehicle_id,
                kind=member.kind,
                injected=injected,
                onset_s=onset,
                true_peak=(float(peak[0]), float(peak[1])),
                estimated_peak_quiet=(float(record.peak_quiet[0]), float(record.peak_quiet[1])),
                estimated_peak_faulty=(float(record.peak_faulty[0]), float(record.peak_faulty[1])),
                sent=record.sent,
                lost=record.lost,
                estimates=record.estimates,
                last_estimate_seq=None if record.last_estimate is None else record.last_estimate.seq,
                fault_alarms=tuple(sorted({e.alarm.kind for e in after_onset})),
                first_alarm_after_onset_s=None if first is None or onset_ns is None else (first - onset_ns) / 1e9,
                false_alarms=false_alarms,
                other_alarms=tuple(sorted({e.alarm.kind for e in raised if e.alarm.kind not in FAULT_ALARM_KINDS})),
                fault_started=started,
                conditions=describe_conditions(member.scenario),
            )
        )
    return FleetSummary(report=report, vehicles=vehicles)


def run_fleet(
    config: FleetConfig,
    *,
    on_progress: Callable[[Progress], None] | None = None,
    stop: threading.Event | None = None,
    progress_period_s: float = 1.0,
    members: Sequence[FleetMember] | None = None,
) -> FleetSummary:
    """Build the fleet (or use ``members``), publish it for ``duration_s`` and summarise.

    Raises MixError / ScenarioError for a bad mix, TransportError if zenoh cannot be reached.
    """
    if members is None:
        members = config.members()
    source = TruthTracker(SimulatedSource([m.vehicle_id for m in members], [m.scenario for m in members]))
    log: TextIO | None = None
    session = open_session(config.transport)
    try:
        reported = report_payloads(session, members, config.publisher.prefix)
        if config.log_path is not None:
            log = config.log_path.open("w")
        with FleetPublisher(
            session,
            source,
            config.publisher,
            onset_s=[m.fault_onset_s for m in members],
            log=log,
        ) as publisher:
            report = publisher.run(
                config.duration_s, stop=stop, on_progress=on_progress, progress_period_s=progress_period_s
            )
            summary = summarize(members, report, source.peak, publisher.deadline_ns)
            return dataclasses.replace(summary, payloads_reported=reported)
    finally:
        close_session(session)
        if log is not None:
            log.close()


def report_payloads(session: Any, members: Sequence[FleetMember], prefix: str, wait_s: float = 5.0) -> int:
    """Report each loaded vehicle's payload on its payload key before its first sample, so the service models it
    loaded from the start (docs/math.md 12.5); returns how many reached a subscriber. Waits at most ``wait_s`` for
    the service once: if it is not there, the rest are sent without waiting (and lost, as the service is)."""
    reached = 0
    for member in members:
        if member.scenario.payload_kg > 0.0:
            matched = report_payload(session, member.vehicle_id, member.scenario.payload_kg, prefix, wait_s)
            reached += matched
            wait_s = wait_s if matched else 0.0
    return reached


def write_summary_json(path: Path, summary: FleetSummary) -> None:
    path.write_text(json.dumps(summary.to_dict(), indent=2, allow_nan=True))
