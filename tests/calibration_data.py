"""A healthy drive of a physical car simulated by the project's own model, shared by the calibration tests.

Simulated once per test process (about 15 s): the calibration tests of synth, of the command line and of
the REST API all start from the same minute of driving.
"""

from __future__ import annotations

import tempfile
from functools import lru_cache
from pathlib import Path

from agv_fe.benchmarks import REFERENCE_CAR
from edge_client.recording import write_recording
from edge_client.scenario import Manoeuvre, Scenario, SensorNoise, SpeedPoint
from edge_client.simulation import simulate_plant
from synth.calibration import Drive
from synth.params import VehicleParams

#: A physical car with everything calibration identifies switched on.
CAR = REFERENCE_CAR
#: What the car's data sheet gives.
BASE = {
    name: getattr(CAR, name)
    for name in ("mass_kg", "front_axle_distance_m", "rear_axle_distance_m", "wheel_radius_m", "yaw_inertia_kgm2")
}
#: A saloon's centre-of-gravity height.
CG_HEIGHT_M = 0.55
NOISE = SensorNoise(vx_sigma_mps=0.05, r_sigma_radps=0.005)


def simulated_drive(
    name: str, duration_s: float, speeds, manoeuvres, seed: int = 3, vehicle: VehicleParams = CAR, faults=()
) -> Drive:
    """The car driven by the project's plant (RK4, 1 ms) through a speed profile and open-loop manoeuvres, with
    ``faults`` (edge_client.faults) on its actuators."""
    scenario = Scenario(
        name=name,
        duration_s=duration_s,
        initial_speed_mps=speeds[0][1],
        vehicle=vehicle,
        speed_profile=[SpeedPoint(t_s=t, speed_mps=v) for t, v in speeds],
        manoeuvres=manoeuvres,
        noise=NOISE,
        seed=seed,
        faults=tuple(faults),
    )
    rec = simulate_plant([scenario])
    return Drive(t=rec.t, y=rec.y[:, 0, :], u=rec.u[:, 0, :], name=name)


@lru_cache(maxsize=1)
def healthy_drive() -> Drive:
    """A minute of ordinary driving: speed changes between 9 and 20 m/s, turns, lane changes, slaloms."""
    return _healthy(CAR)


@lru_cache(maxsize=1)
def healthy_drive_with_load_transfer() -> Drive:
    """The same minute by the car with a centre-of-gravity height (CG_HEIGHT_M): braking in its turns moves load
    between the axles (docs/math.md 12.4)."""
    return _healthy(CAR.model_copy(update={"cg_height_m": CG_HEIGHT_M}))


@lru_cache(maxsize=1)
def healthy_drive_on_hills() -> Drive:
    """The same minute on a road that climbs and descends (grades from -3 % to +5 %, period 23 s), with the grade
    the car reports: the weight's pull R_w M_v g sin(grade) acts on it as a torque fault would (docs/math.md
    12.6)."""
    return _on_hills(CAR)


@lru_cache(maxsize=1)
def healthy_drive_on_hills_with_load_transfer() -> Drive:
    """The minute on hills by the car with a centre-of-gravity height: its load transfer follows the torque it
    sends (the tyres' force on the road), the weight's pull moves none (docs/math.md 12.6)."""
    return _on_hills(CAR.model_copy(update={"cg_height_m": CG_HEIGHT_M}))


#: The load of the loaded minute: a fifth of the car's mass.
PAYLOAD_KG = 0.2 * CAR.mass_kg


def loaded(vehicle: VehicleParams, payload_kg: float) -> VehicleParams:
    """The project's model of ``vehicle`` carrying ``payload_kg`` at its centre of gravity: more mass to accelerate,
    the rolling resistance in proportion to the weight, the lateral motion as it was (the tyres' cornering
    stiffnesses grow with the load they carry, so per kilogram the lateral forces stay the same)."""
    return vehicle.model_copy(
        update={
            "effective_mass_kg": vehicle.effective_mass_kg + payload_kg,
            "rolling_resistance_n": vehicle.rolling_resistance_n * (vehicle.mass_kg + payload_kg) / vehicle.mass_kg,
        }
    )


@lru_cache(maxsize=1)
def loaded_drive_on_hills() -> Drive:
    """The minute on the hills of :func:`healthy_drive_on_hills` by the car carrying PAYLOAD_KG, with the grade it
    reports (the weight's pull is the loaded car's); ``payload_kg`` is left 0 for the caller to state."""
    return _on_hills(loaded(CAR, PAYLOAD_KG), CAR.mass_kg + PAYLOAD_KG)


def _on_hills(vehicle: VehicleParams, weight_kg: float | None = None) -> Drive:
    import dataclasses

    import numpy as np

    from edge_client.faults import SinusoidalFault, fault_tables
    from synth.params import STANDARD_GRAVITY_MPS2

    weight_torque = vehicle.wheel_radius_m * (weight_kg or vehicle.mass_kg) * STANDARD_GRAVITY_MPS2
    pull = SinusoidalFault(
        channel="torque", amplitude=0.04 * weight_torque, omega_radps=0.27, offset=-0.01 * weight_torque
    )
    drive = _healthy(vehicle, (pull,))
    grade = np.arcsin(-fault_tables((pull,), drive.t)[0][:, 0] / weight_torque)
    return dataclasses.replace(drive, name="hills", grade=grade)


def _healthy(vehicle: VehicleParams, faults=()) -> Drive:
    speeds = [(0, 10), (7, 18), (12, 18), (18, 9), (24, 9), (30, 20), (38, 20), (44, 12), (50, 12), (56, 17), (60, 17)]
    manoeuvres = [
        Manoeuvre(kind="slalom", start_s=1, duration_s=5, amplitude_rad=0.03),
        Manoeuvre(kind="turn", start_s=13, duration_s=4, amplitude_rad=0.04, ramp_s=0.5),
        Manoeuvre(kind="lane_change", start_s=25, duration_s=4, amplitude_rad=-0.04),
        Manoeuvre(kind="turn", start_s=39, duration_s=4, amplitude_rad=-0.03, ramp_s=0.4),
        Manoeuvre(kind="slalom", start_s=50, duration_s=6, amplitude_rad=0.035),
    ]
    return simulated_drive("healthy", 60.0, speeds, manoeuvres, vehicle=vehicle, faults=faults)


def csv_text(drive: Drive) -> str:
    """The drive in the replay CSV format."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "drive.csv"
        write_recording(out, drive.t, drive.y, drive.u)
        return out.read_text()
