"""A caller's cancel stops a running estimate or diagnosis (estimation/cancel.py): the Calibrate
action's cancel used to wait for the end of the stage, a diagnosis taking minutes."""

import threading

import pytest

from laser_calib.diagnosis.engine import diagnose
from laser_calib.estimation.cancel import Cancelled, cancellable
from laser_calib.estimation.estimate import EstimateOptions, estimate
from laser_calib.sim.simulation import paper_session


class CancelAfter:
    """requested() that turns true at its ``count``-th call: the cancel arrives mid-fit."""

    def __init__(self, count: int):
        self.count, self.calls = count, 0

    def __call__(self) -> bool:
        self.calls += 1
        return self.calls >= self.count


@pytest.mark.parametrize("method", ["lm", "ekf"])
def test_a_cancel_stops_the_estimate_at_its_next_model_evaluation(method):
    session = paper_session("paper-7dof", 0)
    options = EstimateOptions(method=method, spot_sigma=session.noise.spot_sigma, joint_sigma=session.noise.joint_sigma)
    requested = CancelAfter(3)
    with pytest.raises(Cancelled), cancellable(requested):
        estimate(session.nominal, session.samples, options)
    assert requested.calls == 3  # asked at each evaluation, and nothing evaluated after the cancel
    # outside the block the same estimate runs to its end
    assert estimate(session.nominal, session.samples, options).fit.converged


def test_a_cancel_stops_the_diagnosis():
    session = paper_session("paper-4dof", 0)
    requested = CancelAfter(50)
    with pytest.raises(Cancelled), cancellable(requested):
        diagnose(session.nominal, session.samples, spot_sigma=session.noise.spot_sigma,
                 joint_sigma=session.noise.joint_sigma)
    assert requested.calls == 50


def test_a_cancel_reaches_only_its_own_work():
    """The estimator node serves ~/estimate in other threads while a goal runs: a goal's cancel
    must not stop them."""
    session = paper_session("paper-4dof", 0)
    options = EstimateOptions(spot_sigma=session.noise.spot_sigma, joint_sigma=session.noise.joint_sigma)
    results = []
    with cancellable(lambda: True):
        other = threading.Thread(target=lambda: results.append(estimate(session.nominal, session.samples, options)))
        other.start()
        other.join()
    assert results and results[0].fit.converged


def test_an_estimate_canceled_or_refused_leaves_no_folder_it_made(tmp_path):
    """run_calibration makes its output folder before the estimate (one that cannot be made is refused
    first); a canceled goal's, or a refused request's, folder was left behind empty."""
    from laser_calib.io.errors import InputError
    from laser_calib.session.estimate import run_calibration
    session = paper_session("paper-4dof", 0)
    options = EstimateOptions(spot_sigma=session.noise.spot_sigma, joint_sigma=session.noise.joint_sigma)
    with pytest.raises(Cancelled), cancellable(lambda: True):
        run_calibration(session.nominal, session.samples, options, tmp_path / "new" / "out")
    with pytest.raises(InputError):  # two poses: too few spots for the errors
        run_calibration(session.nominal, session.samples.subset(slice(0, 2)), options, tmp_path / "new" / "out")
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "kept").mkdir()  # a folder that was there stays
    with pytest.raises(Cancelled), cancellable(lambda: True):
        run_calibration(session.nominal, session.samples, options, tmp_path / "kept")
    assert (tmp_path / "kept").is_dir()
