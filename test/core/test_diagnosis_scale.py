"""The diagnosis at scale keeps its answers: the screen by per-fold QR factors
equals least squares on the stacked rows, warm-started folds give the cold
folds' choice and held-out figures, a candidate whose fold fit diverges is
rejected without a RuntimeWarning, the detector's poses are runs of
consecutive poses over the whole session, above SELECTION_POSES the selection
runs on part of the poses and every figure is of all of them, and residuals
by blocks equal the whole evaluation."""

import warnings
from dataclasses import replace

import numpy as np
import pytest

from laser_calib.diagnosis import engine
from laser_calib.diagnosis.data import SpotData
from laser_calib.diagnosis.detector import Basis, OffsetRegression, submodels
from laser_calib.diagnosis.engine import DETECTOR_POSES, DETECTOR_RUNS, candidate_pool, detector_rows, run
from laser_calib.diagnosis.fitter import Fitter, paired_p
from laser_calib.diagnosis.options import DiagnoseOptions
from laser_calib.diagnosis.selection import select
from laser_calib.effects.catalog import screen_shape
from laser_calib.effects.effect_model import EffectModel
from laser_calib.effects.screen import ScreenShape
from laser_calib.estimation.estimate import estimate_model
from laser_calib.estimation.problem import residuals_at
from laser_calib.measurement.base import whiten
from test_diagnosis import NOISE, library_session


@pytest.fixture(scope="module")
def backlash():
    session = library_session("paper-7dof", "backlash")
    data = SpotData(session.nominal, session.cal)
    options = DiagnoseOptions(spot_sigma=NOISE.spot_sigma, joint_sigma=NOISE.joint_sigma)
    return data, options


def stacked_screen(fitter, current, pool):
    """The linearised cross-validation on the stacked whitened rows (lstsq per fold)."""
    model = EffectModel(fitter.base, current.effects + tuple(pool))
    x = np.concatenate([current.estimate.values, np.zeros(len(model.names) - len(current.model.names))])
    res = model.residuals(x, True)
    r, jac = whiten(res, fitter.reference.whitener(res))
    jac = jac * model.scales
    pose_of_row = np.repeat(np.arange(len(res.r)), res.r.shape[1] * res.r.shape[2])
    kept = list(np.flatnonzero(current.estimate.identifiable))
    out = {}
    for effect, block in zip(pool, model.blocks[len(current.effects):]):
        columns = kept + list(range(model.n_geometric + block.start, model.n_geometric + block.stop))
        chi2 = 0.0
        for k in range(fitter.options.folds):
            held = (fitter.fold == k)[pose_of_row]
            step = np.linalg.lstsq(jac[~held][:, columns], r[~held], rcond=None)[0]
            chi2 += float(((r[held] - jac[held][:, columns] @ step) ** 2).sum())
        out[effect.label] = chi2 / (res.valid.sum() * res.r.shape[2])
    return out


def test_screen_by_factors_equals_least_squares_on_the_stacked_rows(backlash):
    data, options = backlash
    fitter = Fitter(data, options)
    current = fitter.start()
    pool = candidate_pool(data, fitter, options, [])
    expected = stacked_screen(fitter, current, pool)
    screened = fitter.screen(current, pool)
    # the same solves in another factorisation: equal to rounding (J's condition ~1e4)
    np.testing.assert_allclose([chi2 for _, chi2, _ in screened], [expected[e.label] for e, _, _ in screened],
                               rtol=1e-9)
    assert [e.label for e, _, _ in screened] == sorted(expected, key=expected.get)


class ColdFolds(Fitter):
    """Every fold fit from nominal (geometric 0, effects 0) with the LM restarts."""

    def fit(self, effects, x0):
        fitted = super().fit(effects, x0)
        model = fitted.model
        cv_chi2 = np.zeros(len(self.fold))
        for k in range(self.options.folds):
            held = self.fold == k
            train = estimate_model(model.subset(~held), self.fit_options, None, np.zeros(len(model.names)))
            cv_chi2[held] = self.scored(model.subset(held), train.values)[0]
        return replace(fitted, cv_chi2=cv_chi2)


def test_warm_started_folds_give_the_cold_choice_and_held_out_figures(backlash):
    data, options = backlash
    options = replace(options, max_effects=1, shortlist=2)
    warm, cold = Fitter(data, options), ColdFolds(data, options)
    warm_fits, warm_rounds, _ = select(warm, candidate_pool(data, warm, options, []), options)
    cold_fits, cold_rounds, _ = select(cold, candidate_pool(data, cold, options, []), options)
    assert [f.label for f in warm_fits] == [f.label for f in cold_fits] == ["geometric", "geometric + backlash (joint 6)"]
    assert [r.outcome for r in warm_rounds[0]] == [r.outcome for r in cold_rounds[0]]
    # LM stops within 1e-4 standard deviations of the minimum from either start, which
    # moves a held-out chi^2 (~ 1 per value) by far less than 1e-4 of itself
    for w, c in zip(warm_fits, cold_fits):
        np.testing.assert_allclose(w.cv_chi2, c.cv_chi2, rtol=1e-4, atol=1e-6)


def test_a_diverging_candidate_is_rejected_without_a_warning(backlash):
    data, options = backlash
    fitter = Fitter(data, options)
    current = fitter.start()
    effect = screen_shape(data.robot)
    model = EffectModel(fitter.base, (effect,))
    # a fold fit run off to sizes at which the screen's shape overflows
    x = np.concatenate([current.estimate.values, np.full(len(effect.params), 1e200)])
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        chi2, _, _ = fitter.scored(model, x)
        assert np.isinf(chi2).any() and not np.isnan(chi2).any()
        diverged = replace(current, cv_chi2=np.where(np.isfinite(chi2), current.cv_chi2, chi2))
        assert paired_p(current, diverged) == 1.0


def test_detector_rows_are_runs_of_consecutive_poses_over_the_session():
    assert detector_rows(DETECTOR_POSES, 0) is None
    n = 200_000
    rows = detector_rows(n, 0)
    assert len(rows) == DETECTOR_POSES and np.all(np.diff(rows) > 0) and rows[-1] < n
    assert np.count_nonzero(np.diff(rows) > 1) == DETECTOR_RUNS - 1
    # one run in each tenth of the session
    assert np.array_equal(np.unique(rows * DETECTOR_RUNS // n), np.arange(DETECTOR_RUNS))
    np.testing.assert_array_equal(rows, detector_rows(n, 0))


def test_progress_counts_the_fits_of_each_model_and_stays_out_of_the_result(backlash):
    data, options = backlash
    calls = []
    options = replace(options, max_effects=1, shortlist=1, nested=False, progress=lambda *call: calls.append(call))
    diagnosis = run(data, options)
    fits = [(done, total) for done, total, note in calls if total is not None]
    assert fits and all(1 <= done <= total == options.folds + 1 for done, total in fits)
    assert any(note.startswith("selection: geometric + ") for _, _, note in calls)
    assert diagnosis.options.progress is None


def test_scored_distances_are_nan_where_a_spot_is_not_measured(backlash):
    data, options = backlash
    samples = data.samples
    spots = samples.spots.copy()
    spots[:5, 1] = np.nan  # the second laser's spot not seen on five poses
    data = SpotData(data.robot, replace(samples, spots=spots))
    fitter = Fitter(data, options)
    chi2, distances, n_values = fitter.scored(EffectModel(fitter.base, ()), np.zeros(len(fitter.base.names)))
    assert np.isnan(distances[:5, 1]).all() and np.isfinite(distances[5:]).all() and np.isfinite(chi2).all()
    assert n_values == 2 * (distances.size - 5)


def test_selection_on_part_of_the_poses_scores_every_pose(monkeypatch):
    """Above SELECTION_POSES the rounds see that many poses; the stages (refitted) and
    the nested held-out error are of every pose, and the effect is still found."""
    session = library_session("paper-7dof", "backlash", n_cal=160)
    monkeypatch.setattr(engine, "SELECTION_POSES", 100)
    calls = []
    options = DiagnoseOptions(spot_sigma=NOISE.spot_sigma, joint_sigma=NOISE.joint_sigma, max_effects=1, shortlist=2,
                              progress=lambda *call: calls.append(call))
    diagnosis = run(SpotData(session.nominal, session.cal), options)
    assert [s.label for s in diagnosis.stages] == ["geometric", "geometric + backlash (joint 6)"]
    assert any("selected on 100 of the 160 poses" in note for note in diagnosis.notes)
    # each nested fold's chosen model refitted on its 128 training poses, on the progress line
    assert sum("on all 128 training poses" in note for _, _, note in calls) == options.folds
    measured = 2 * int(session.cal.seen.sum())
    for stage in diagnosis.stages:
        fitted = stage.fitted
        assert fitted.n_values == fitted.estimate.fit.n_values == measured
        assert np.isfinite(fitted.cv[session.cal.seen]).all()
    assert diagnosis.nested.shape == session.cal.spots.shape[:2]
    assert np.isfinite(diagnosis.nested[session.cal.seen]).all()
    # the nested figure is a held-out one: not below the final model's in-sample error
    final = diagnosis.stages[-1].fitted
    assert np.sqrt(np.nanmean(diagnosis.nested ** 2)) > np.sqrt(np.nanmean(final.cal ** 2))


def test_residuals_by_blocks_with_jacobians_equal_the_whole_evaluation(backlash):
    """The verdict's and the detector's residuals are evaluated by blocks of poses
    (bounded transients at 200,000 poses): the same values bit for bit."""
    data, _ = backlash
    pool = data.candidates()
    model = EffectModel(data.base(), (pool[0], next(e for e in pool if isinstance(e, ScreenShape))))
    x = np.random.default_rng(0).normal(size=len(model.names)) * model.scales * 0.1
    whole, blocks = model.residuals(x, True), residuals_at(model, x, chunk=16, jacobian=True)
    for name in ("r", "valid", "jac", "jac_q", "predicted"):
        np.testing.assert_array_equal(getattr(blocks, name), getattr(whole, name))


def test_a_sub_models_features_are_its_columns_of_all_features():
    """The detector forms only a sub-model's columns, from only the basis functions they use
    (permutation importance predicts 146 times): the same values as those columns of every
    feature, for a pair as its product and as the products of its splines (the compensator's
    tensor), inside the inputs' range and beyond it (a test pose)."""
    rng = np.random.default_rng(0)
    z, g = rng.normal(size=(50, 5)), rng.normal(size=(50, 3))
    basis = Basis.of(z, 3, 1.7)
    beyond = np.hstack([3.0 * rng.normal(size=(50, 5)), g])
    for X in (np.hstack([z, g]), beyond):
        for columns in submodels(basis, 5, 3)[::7]:
            regression = OffsetRegression(basis, 5, 1.0, columns)
            np.testing.assert_array_equal(regression.features(X), regression.all_features(X)[:, columns])
        tensor = replace(basis, tensor=True)
        n = tensor.splines_per_input
        for k, p in ((0, 0), (4, 2), (2, 1)):   # an input's splines and a pair's products, on direction 1
            local = np.concatenate([np.arange(k * n, (k + 1) * n), 5 * n + p * n * n + np.arange(n * n)])
            regression = OffsetRegression(tensor, 5, 1.0, tensor.width + local)
            np.testing.assert_array_equal(regression.features(X), regression.all_features(X)[:, tensor.width + local])
