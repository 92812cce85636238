"""The fleet state: observer banks per profile, alarms and the event hook; no transport, no web, no storage."""

from service.fleet.alarms import AlarmBook, AlarmChange, AlarmRecord, LevelDetector, UnknownAlarm
from service.fleet.bank import ProfileBank
from service.fleet.engine import EngineConfig, FleetEngine, FleetError, UnknownProfile, UnknownVehicle
from service.fleet.events import EventBus, FleetEvent, Subscription
from service.fleet.tick import TickResult
from service.fleet.vehicle import REJECT_REASONS, Vehicle

__all__ = [
    "REJECT_REASONS",
    "AlarmBook",
    "AlarmChange",
    "AlarmRecord",
    "EngineConfig",
    "EventBus",
    "FleetEngine",
    "FleetError",
    "FleetEvent",
    "LevelDetector",
    "ProfileBank",
    "Subscription",
    "TickResult",
    "UnknownAlarm",
    "UnknownProfile",
    "UnknownVehicle",
    "Vehicle",
]
