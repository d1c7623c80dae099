"""The flexible detector's basis (diagnosis.detector.Basis): what one pair's
sub-model can represent exactly."""

import numpy as np

from laser_calib.diagnosis.detector import Basis, OffsetRegression, submodels


def pair_columns(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(P,b) basis of readings q (P,3) and the columns of the sub-model of direction 0 with the pair (q2, q3)."""
    basis = Basis.of(q, q.shape[1])
    values = basis(q)
    pair = list(map(tuple, basis.pairs)).index((1, 2))
    n_splines = len(submodels(basis, q.shape[1], 1)[0])
    columns = submodels(basis, q.shape[1], 1)[q.shape[1] + pair]
    assert len(columns) > 2 * n_splines
    return values, columns


def test_a_pair_spans_the_products_of_both_joints_first_harmonics():
    # sin q2 sin(q3 + phi) over +-170 deg: one term of a Fourier series in both angles, which
    # additive splines of each reading and their bilinear product leave in large part.
    rng = np.random.default_rng(3)
    q = rng.uniform(-3.0, 3.0, size=(200, 3))
    values, columns = pair_columns(q)
    for phase in (0.0, 1.0, 2.5):
        target = np.sin(q[:, 1]) * np.sin(q[:, 2] + phase)
        coefficients, *_ = np.linalg.lstsq(values[:, columns], target, rcond=None)
        assert np.max(np.abs(values[:, columns] @ coefficients - target)) < 1e-9


def test_the_regression_features_are_direction_times_basis():
    rng = np.random.default_rng(4)
    q = rng.uniform(-1.0, 1.0, size=(30, 3))
    basis = Basis.of(q, 3)
    g = rng.normal(size=(30, 2))
    features = OffsetRegression(basis, 3).all_features(np.hstack([q, g]))
    width = basis(q).shape[1]
    np.testing.assert_allclose(features[:, width:2 * width], g[:, 1:2] * basis(q))
