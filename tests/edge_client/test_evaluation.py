import numpy as np

from edge_client.evaluation import DetectionRule, compare, detection
from edge_client.simulation import ekf_factory, observer_factory


def test_detection_delay_and_false_detections():
    t = np.arange(0, 10, 0.01)
    est = np.where(t >= 5.2, 20.0, 0.0)
    est[(t >= 1.0) & (t < 1.5)] = 30.0  # a 0.5 s excursion before the onset: one false detection
    delay, false = detection(t, est, threshold=15.0, hold_s=0.3, onset=5.0)
    assert false == 1
    assert abs(delay - 0.5) < 0.02  # 0.2 s to cross + 0.3 s hold
    assert detection(t, np.zeros_like(t), 15.0, 0.3, 5.0) == (None, 0)


def test_compare_runs_both_estimators_on_the_same_data(paper_gains_order1):
    c = compare(
        "paper-2",
        {"observer": observer_factory(paper_gains_order1), "EKF": ekf_factory(paper_gains_order1)},
        seeds=1,
        rule=DetectionRule(),
        batch=50,
    )
    assert set(c.scores) == {"observer", "EKF"}
    # same record: identical truth in both example results
    np.testing.assert_array_equal(c.example["observer"].f, c.example["EKF"].f)
    assert c.state_bytes["EKF"] > c.state_bytes["observer"]
    assert c.step_us_batch["observer"] > 0 and c.step_us_batch["EKF"] > 0
