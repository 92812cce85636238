"""Built-in scenarios: the paper's two (Section 4) and evaluation cases.

The paper gives its scenarios in words and figures only; the choices made to
turn them into numbers are listed in docs/scenarios.md. Every scenario keeps
the vehicle inside the design bounds of eq. (13) (a test checks it).
"""

from __future__ import annotations

from collections.abc import Callable

from edge_client.faults import BiasFault, LossOfEffectivenessFault, SinusoidalFault
from edge_client.scenario import REALISTIC_NOISE, Gust, Manoeuvre, Scenario, SensorNoise, SpeedPoint

#: The observer's initial state in both paper scenarios: [5, -1, 0].
PAPER_OBSERVER_INITIAL_STATE = (5.0, -1.0, 0.0)


def paper_1(noise: SensorNoise | None = None, seed: int = 0) -> Scenario:
    """Section 4.1: straight, right turn, straight, right turn at about 10 m/s.

    Torque bias of 30 N m from t = 5 s (eqs. 7-8), repetitive steering fault
    0.1 sin(0.5 t) rad, 800 N lateral wind between 10 and 11 s (NOTES.md).
    """
    return Scenario(
        name="paper-1",
        description="Paper Scenario 1: turns, torque bias, sinusoidal steering fault, wind gust",
        duration_s=20.0,
        initial_speed_mps=10.0,
        speed_profile=(SpeedPoint(t_s=0.0, speed_mps=10.0), SpeedPoint(t_s=20.0, speed_mps=11.0)),
        manoeuvres=(
            Manoeuvre(kind="straight", start_s=0.0, duration_s=4.0),
            Manoeuvre(kind="turn", start_s=4.0, duration_s=4.0, amplitude_rad=-0.03, ramp_s=1.0),
            Manoeuvre(kind="straight", start_s=8.0, duration_s=4.0),
            Manoeuvre(kind="turn", start_s=12.0, duration_s=4.0, amplitude_rad=-0.03, ramp_s=1.0),
        ),
        faults=(
            BiasFault(channel="torque", onset_s=5.0, magnitude=30.0),
            SinusoidalFault(channel="steer", onset_s=0.0, amplitude=0.1, omega_radps=0.5, phase_from_zero=True),
        ),
        gusts=(Gust(start_s=10.0, duration_s=1.0, force_n=800.0),),
        noise=noise or SensorNoise(),
        seed=seed,
        observer_initial_state=PAPER_OBSERVER_INITIAL_STATE,
    )


def paper_2(noise: SensorNoise | None = None, seed: int = 0) -> Scenario:
    """Section 4.2: a lane change between 13 and 21 s; fault amplitudes grow over time.

    Torque loss of effectiveness from t = 4 s at 2 %/s down to 70 % (eqs. 9-11);
    steering bias ramping from 0 to 0.03 rad between 6 and 16 s.
    """
    return Scenario(
        name="paper-2",
        description="Paper Scenario 2: lane change, growing torque loss of effectiveness and steering bias",
        duration_s=25.0,
        initial_speed_mps=8.0,
        speed_profile=(SpeedPoint(t_s=0.0, speed_mps=8.0), SpeedPoint(t_s=10.0, speed_mps=15.0)),
        manoeuvres=(Manoeuvre(kind="lane_change", start_s=13.0, duration_s=8.0, amplitude_rad=0.02),),
        faults=(
            LossOfEffectivenessFault(channel="torque", onset_s=4.0, rate_per_s=0.02, alpha_min=0.7),
            BiasFault(channel="steer", onset_s=6.0, magnitude=0.03, ramp_s=10.0),
        ),
        noise=noise or SensorNoise(),
        seed=seed,
        observer_initial_state=PAPER_OBSERVER_INITIAL_STATE,
    )


def highway(noise: SensorNoise | None = None, seed: int = 0) -> Scenario:
    """About 25 m/s with three lane changes; a steering bias step and a torque loss-of-effectiveness ramp.

    Torque effectiveness falls 2 %/s from t = 10 s to 60 % (a fault of about -90 N m at cruise);
    steering bias of 0.01 rad from t = 22 s. Realistic sensor noise unless told otherwise.
    """
    return Scenario(
        name="highway",
        description="Highway: 25 m/s, lane changes, torque loss of effectiveness ramp, steering bias step",
        duration_s=40.0,
        initial_speed_mps=24.0,
        speed_profile=(SpeedPoint(t_s=0.0, speed_mps=24.0), SpeedPoint(t_s=8.0, speed_mps=26.0)),
        manoeuvres=(
            Manoeuvre(kind="lane_change", start_s=5.0, duration_s=4.0, amplitude_rad=0.012),
            Manoeuvre(kind="lane_change", start_s=16.0, duration_s=4.0, amplitude_rad=-0.012),
            Manoeuvre(kind="lane_change", start_s=30.0, duration_s=5.0, amplitude_rad=0.01),
        ),
        faults=(
            LossOfEffectivenessFault(channel="torque", onset_s=10.0, rate_per_s=0.02, alpha_min=0.6),
            BiasFault(channel="steer", onset_s=22.0, magnitude=0.01),
        ),
        noise=REALISTIC_NOISE if noise is None else noise,
        seed=seed,
    )


def urban(noise: SensorNoise | None = None, seed: int = 0) -> Scenario:
    """About 8 m/s stop-and-go with turns; a torque bias, a sinusoidal steering fault and a wind gust.

    Torque bias of 40 N m from t = 8 s; steering fault 0.02 sin(0.8 (t - 15)) rad from t = 15 s;
    1,000 N lateral gust for 2 s at t = 27 s. Realistic sensor noise unless told otherwise.
    """
    return Scenario(
        name="urban",
        description="Urban: 6-10 m/s, turns, torque bias, sinusoidal steering fault, wind gust",
        duration_s=40.0,
        initial_speed_mps=8.0,
        speed_profile=(
            SpeedPoint(t_s=0.0, speed_mps=8.0),
            SpeedPoint(t_s=10.0, speed_mps=10.0),
            SpeedPoint(t_s=18.0, speed_mps=6.0),
            SpeedPoint(t_s=28.0, speed_mps=9.0),
            SpeedPoint(t_s=40.0, speed_mps=7.0),
        ),
        manoeuvres=(
            Manoeuvre(kind="turn", start_s=3.0, duration_s=5.0, amplitude_rad=0.12, ramp_s=1.0),
            Manoeuvre(kind="turn", start_s=12.0, duration_s=5.0, amplitude_rad=-0.12, ramp_s=1.0),
            Manoeuvre(kind="turn", start_s=22.0, duration_s=4.0, amplitude_rad=0.1, ramp_s=1.0),
            Manoeuvre(kind="slalom", start_s=31.0, duration_s=6.0, amplitude_rad=0.05, period_s=3.0),
        ),
        faults=(
            BiasFault(channel="torque", onset_s=8.0, magnitude=40.0),
            SinusoidalFault(channel="steer", onset_s=15.0, amplitude=0.02, omega_radps=0.8),
        ),
        gusts=(Gust(start_s=27.0, duration_s=2.0, force_n=1000.0),),
        noise=REALISTIC_NOISE if noise is None else noise,
        seed=seed,
    )


BUILTIN_SCENARIOS: dict[str, Callable[..., Scenario]] = {
    "paper-1": paper_1,
    "paper-2": paper_2,
    "highway": highway,
    "urban": urban,
}

#: The scenarios of the accuracy benchmark (docs/benchmarks/accuracy.md), all with realistic noise.
EVALUATION_SCENARIOS = ("paper-1", "paper-2", "highway", "urban")


def builtin_scenario(name: str, noise: SensorNoise | None = None, seed: int = 0) -> Scenario:
    """A built-in scenario by name; KeyError lists the known names."""
    try:
        factory = BUILTIN_SCENARIOS[name]
    except KeyError:
        raise KeyError(f"unknown scenario {name!r}; known: {', '.join(sorted(BUILTIN_SCENARIOS))}") from None
    return factory(noise=noise, seed=seed)
