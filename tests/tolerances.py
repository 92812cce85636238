"""Every numerical tolerance of the test suite, named in one place."""

import math

#: N-TS / 8-rule TS model against the Euler step of eqs. (1)-(2), absolute [state units].
MODEL_EQUALITY_ATOL = 1e-12
#: Membership functions sum to one.
SIMPLEX_ATOL = 1e-12
#: One RK4 step of the plant against a tight reference integration.
PLANT_STEP_ATOL = 1e-9
#: Fault estimate RMSE after 3 s on noise-free paper scenarios, fraction of the fault amplitude.
CONVERGENCE_FRACTION = 0.10
#: The 'h2' cost form against the Kalman filter of the same model at a frozen premise (measured: 1.01).
FROZEN_H2_FORM_COST_RTOL = 1.03
#: A batch step equals the same vehicles stepped one at a time.
BATCH_EQUALITY_ATOL = 1e-9

# -- edge client --------------------------------------------------------------------------------
#: Linearised steady-state lateral response against a long nonlinear plant run, relative.
STEADY_STATE_RTOL = 0.02
#: Latest a fault alarm may arrive after the onset [s] (loss of effectiveness ramps in over seconds).
MAX_ALARM_DELAY_S = 8.0
#: Samples per vehicle that may vanish without error when a router dies (put before zenoh notices).
SILENT_LOSS_PER_VEHICLE = 30

# -- the same quantity computed two ways ---------------------------------------------------------
#: Values one or two floating-point operations apart (a product by a constant, the mirror's sign flips, a
#: recursion against its closed form): the last bits of numbers of order one, absolute.
LAST_BITS_ATOL = 1e-15
#: One formula written two ways (a matrix form against the equations, the observer's output map against its
#: equation written out, a step of a batch against the same vehicle alone): rounding only, relative and absolute.
FORMULA_EQUALITY_RTOL = 1e-12
FORMULA_EQUALITY_ATOL = 1e-12
#: The same through a chain that amplifies rounding (an observer step with gains of order 10^3, the fleet engine's
#: fast and general tick paths stepping other batches, a simulated actuator's applied fault), relative and
#: absolute [state units].
AMPLIFIED_ROUNDING_RTOL = 1e-9
AMPLIFIED_ROUNDING_ATOL = 1e-9
#: A batch's observer step against its equation written out with einsum over the vehicles, relative and absolute.
OBSERVER_EQUATION_TOL = 1e-10
#: A sample mean by trapezoid quadrature on 20,000 intervals against its closed form, relative.
QUADRATURE_RTOL = 1e-9
#: Central differences with step 1e-6 against an analytical Jacobian (truncation and cancellation).
FINITE_DIFFERENCE_TOL = 1e-6
#: The reference integration (DOP853) a plant step is compared with, relative and absolute [state units].
REFERENCE_INTEGRATION_RTOL = 1e-12
REFERENCE_INTEGRATION_ATOL = 1e-13
#: Beyond half a DBC scaling step, for the rounding of the scaled signal value (can2csv).
QUANTISATION_SLACK = 1e-9
#: A signal decoded from CAN against its value before encoding: half the scaling step of the test DBC
#: (tests/edge_client/test_can_log.py) in the protocol's units, plus the slack: 0.01 km/h [m/s], 0.01 deg/s
#: [rad/s], 0.0001 rad [rad], 0.5 N m [N m], 0.001 deg of road grade [rad].
CAN_SPEED_ATOL_MPS = 0.01 / 3.6 / 2 + QUANTISATION_SLACK
CAN_YAW_RATE_ATOL_RADPS = math.radians(0.01) / 2 + QUANTISATION_SLACK
CAN_STEER_ATOL_RAD = 0.0001 / 2 + QUANTISATION_SLACK
CAN_TORQUE_ATOL_NM = 0.5 / 2 + QUANTISATION_SLACK
CAN_GRADE_ATOL_RAD = math.radians(0.001) / 2 + QUANTISATION_SLACK
#: Sample standard deviation of 2,000 samples of simulated sensor noise against its sigma, relative.
NOISE_SIGMA_RTOL = 0.1

# -- estimates written to CSV (9 significant digits) ---------------------------------------------
#: Estimates read back from a replay's CSV against the same estimates in memory, relative and absolute.
CSV_ROUND_TRIP_RTOL = 1e-8
CSV_ROUND_TRIP_ATOL = 1e-9
#: A replay's estimates against the simulation's on the same recording, both read from CSV [N m], [rad].
REPLAY_TORQUE_FAULT_ATOL_NM = 1e-6
REPLAY_STEER_FAULT_ATOL_RAD = 1e-9
#: (alpha - 1) times the demand against the total minus the bias, each read from CSV [N m].
CSV_PRODUCT_ATOL_NM = 1e-4
#: A time stamp on the sample grid against a delay or duration computed in floating point [s].
SAMPLE_GRID_ATOL_S = 1e-9
#: The service's effectiveness stage (biases, total faults) against the offline stage on the same measurements:
#: rows stepped in batches of another size sum in another order [N m], [rad].
STAGE_BATCH_ATOL = 1e-6
#: Detections of a Page CUSUM on 10^7 white Gaussian samples against its design rate (10,000 expected): about
#: four standard deviations of the count, plus the Brook-Evans chain's discretisation (100 states), relative.
PAGE_TEST_RATE_RTOL = 0.04
