"""Which errors the laser spots can separate, on both of the paper's arms."""

import numpy as np

from laser_calib.estimation.identifiability import analyse
from laser_calib.measurement.base import NoiseModel, whiten
from laser_calib.measurement.spot import SpotModel
from laser_calib.sim.simulation import paper_session


def _analysis(case, seed=0):
    session = paper_session(case, seed)
    model = SpotModel(session.nominal, session.samples)
    res = model.residuals(np.zeros(session.nominal.n_params))
    _, jac = whiten(res, NoiseModel(0.001).whitener(res))
    return analyse(jac, model.scales, model.names)


def test_7dof_all_33_errors_identifiable():
    ident = _analysis("paper-7dof")
    assert ident.rank == 33 and ident.free.all() and not ident.merged
    assert np.isfinite(ident.condition)


def test_4dof_has_two_sum_only_pairs_merged():
    """alpha_1 = 0 and alpha_4 = 0: d1/d2 and d4/slm_z act only as sums (conventions.md)."""
    ident = _analysis("paper-4dof")
    assert ident.rank == 19
    assert set(ident.merged) == {"d2", "slm_z"}
    assert "d1" in ident.merged["d2"] and "d4" in ident.merged["slm_z"]
    assert sorted(ident.null_combinations) == sorted(["+1.00 d1 -1.00 d2", "+1.00 d4 -1.00 slm_z"])
