"""The online EKF (one pose per step) against the offline estimate with the same prior."""

import numpy as np

from laser_calib.estimation.estimate import EstimateOptions, estimate
from laser_calib.estimation.online import OnlineEkf
from laser_calib.session.estimate import online_options
from laser_calib.sim.simulation import paper_session


def test_online_ekf_ends_near_the_offline_map_estimate():
    session = paper_session("paper-7dof", 2)
    options = EstimateOptions(spot_sigma=session.noise.spot_sigma, joint_sigma=session.noise.joint_sigma,
                              prior=True)
    online = OnlineEkf(session.nominal, options)
    assert not online.identifiable.any()
    for q, spots in zip(session.samples.q, session.samples.spots):
        online.update(q, spots)
    offline = estimate(session.nominal, session.samples, options)
    # Same posterior, linearised once per pose instead of iterated: within one std.
    assert np.all(np.abs(online.errors - offline.errors) < offline.std)
    assert np.allclose(online.std, offline.std, rtol=0.2)
    assert online.identifiable.all() and online.n_samples == len(session.samples)


def test_online_ekf_skips_unseen_spots_and_resets():
    session = paper_session("paper-4dof", 3)
    online = OnlineEkf(session.nominal, EstimateOptions(spot_sigma=0.001))
    online.update(session.samples.q[0], np.full((2, 2), np.nan))
    assert np.all(online.errors == 0) and online.n_samples == 1
    online.update(session.samples.q[1], session.samples.spots[1])
    assert np.any(online.errors != 0)
    online.reset()
    assert online.n_samples == 0 and np.all(online.errors == 0)



def test_the_estimator_nodes_default_options_run_the_filter():
    """The node's spot_sigma 0 leaves both sigmas to be estimated, which a running filter
    cannot: it takes its default spot sigma and no joint noise (it raised a TypeError on the
    first pose when the batch estimate began to estimate the joint-reading sigma)."""
    session = paper_session("paper-4dof", 3)
    online = OnlineEkf(session.nominal, online_options(0.0))
    for q, spots in zip(session.samples.q[:5], session.samples.spots[:5]):
        online.update(q, spots)
    assert np.all(np.isfinite(online.errors)) and np.any(online.errors != 0)

def test_a_pose_delivered_late_is_filtered_in_its_place():
    """The estimator node takes samples as DDS delivers them; a subscriber matched late gets
    the latched history after a live sample (seen in test_crash_resume: sample 1, then 0).
    take() puts the late pose in its stamp order: the result is the in-order filter's, exactly."""
    s = paper_session("paper-7dof", seed=2, n_per_span=6)
    stamps = np.arange(len(s.samples.q), dtype=float)
    in_order, late = OnlineEkf(s.nominal), OnlineEkf(s.nominal)
    for k in range(len(stamps)):
        in_order.take(stamps[k], s.samples.q[k], s.samples.spots[k])
    for k in [1, 0] + list(range(2, len(stamps) - 3)) + [len(stamps) - 1, len(stamps) - 3, len(stamps) - 2]:
        late.take(stamps[k], s.samples.q[k], s.samples.spots[k])
    np.testing.assert_array_equal(late.errors, in_order.errors)
    np.testing.assert_array_equal(late.covariance, in_order.covariance)
    np.testing.assert_array_equal(late.samples().q, s.samples.q)
