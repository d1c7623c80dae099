"""Plots and the markdown report of a diagnosis (matplotlib, no display);
the style of ../report.py."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from laser_calib.report.plots import pyplot, save_figure
from laser_calib.diagnosis.result import Analysis, Diagnosis
from laser_calib.diagnosis.structure import Series, Test, binned_test



def _find(analysis: Analysis, response: str, covariate: str) -> tuple[Series, Series] | None:
    r = next((s for s in analysis.responses if s.name == response), None)
    c = next((s for s in analysis.covariates if s.name == covariate), None)
    return None if r is None or c is None else (r, c)


def deciding_test(diagnosis: Diagnosis) -> Test | None:
    """The covariate the geometric residual followed most strongly (the first
    effect's evidence), or, with nothing found, the strongest remaining one."""
    tests = diagnosis.before.tests or diagnosis.after.tests
    return tests[0] if tests else None


def plot_residual(diagnosis: Diagnosis, test: Test, path: Path) -> None:
    """The response against the covariate, geometric fit and final model side by
    side: every pose (or spot) and the binned means with their standard errors."""
    fig, axes = pyplot().subplots(1, 2, figsize=(10, 3.8), sharey=True)
    for ax, (title, analysis) in zip(axes, (("geometric", diagnosis.before), (diagnosis.final.label, diagnosis.after))):
        found = _find(analysis, test.response, test.covariate)
        if found is None:
            continue
        response, covariate = found
        shape = response.values.shape
        x = np.broadcast_to(covariate.values if covariate.values.ndim == len(shape) else covariate.values[:, None],
                            shape)
        keep = response.weights > 0
        ax.plot(x[keep] * covariate.factor, response.values[keep] * response.factor, ".", color="0.6", ms=3,
                label="poses" if response.level == "pose" else "spots")
        binned = binned_test(response, covariate)
        if binned is not None:
            ax.errorbar(binned.centres, binned.means, yerr=binned.errors, fmt="o-", color="tab:red", capsize=3,
                        label=f"bin means (F = {binned.f:.3g}, p = {binned.p:.2g} before adjustment)")
        ax.axhline(0.0, color="k", lw=0.6)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel(f"{test.covariate} ({test.covariate_unit})" if test.covariate_unit else test.covariate)
        ax.legend(fontsize=7)
    axes[0].set_ylabel(f"{test.response} ({test.response_unit})")
    spread = max(abs(v) for v in axes[0].get_ylim())
    axes[0].set_ylim(-spread, spread)
    save_figure(fig, path)


def plot_stages(stages: list[dict], path: Path) -> None:
    """RMS spot error per stage on the calibration, held-out (cross-validated) and test poses."""
    fig, ax = pyplot().subplots(figsize=(7, 3.2))
    labels = [f"{k}" for k in range(len(stages))]
    width = 0.27
    for offset, key, colour in ((-width, "cal", "tab:blue"), (0.0, "cv", "tab:orange"), (width, "test", "tab:green")):
        values = [s[key]["rms_mm"] if s[key] and s[key]["rms_mm"] is not None else np.nan for s in stages]
        ax.bar(np.arange(len(stages)) + offset, values, width, label=key, color=colour)
    ax.set_xticks(np.arange(len(stages)), labels)
    ax.set_xlabel("stage (table above)")
    ax.set_ylabel("RMS spot error (mm)")
    ax.legend(fontsize=7)
    save_figure(fig, path)


def _stat(s: dict | None, key: str) -> str:
    return "-" if not s or s[key] is None else f"{s[key]:.3f}"


def markdown(diagnosis: Diagnosis, result: dict, plots: dict[str, str]) -> str:
    samples, test = diagnosis.samples, diagnosis.test_samples
    noise = result["noise"]
    lines = [f"# Diagnosis of {diagnosis.robot.name}: what the geometric model lacks", "",
             f"{len(samples)} calibration poses" + (f", {len(test)} test poses" if test is not None else "")
             + f"; spot sigma {noise['spot_sigma_m'] * 1e3:.3g} mm ({noise['spot_sigma_source']}), joint-reading "
               f"sigma {np.degrees(noise['joint_sigma_rad']):.3g} deg ({noise['joint_sigma_source']}); "
               f"{diagnosis.options.folds}-fold cross-validation; {diagnosis.wall_time:.1f} s.", "",
             f"**Verdict: {result['verdict']}.** {result['evidence']}", ""]
    if diagnosis.failure:
        lines += [f"**Error: {diagnosis.failure}.** The calibrated robot written beside this report shows where the "
                  "final fit went; it is no calibration.", ""]
    warnings = [w for w in result["warnings"] if w != diagnosis.failure]
    if warnings:
        lines += [f"**Warning:** {w}." for w in warnings] + [""]
    if diagnosis.notes:
        lines += [f"Note: {n}." for n in diagnosis.notes] + [""]
    if diagnosis.robot.chain is not None:
        lines += ["Joints (the covariates q1..qN, the effects' joint numbers): "
                  + ", ".join(f"{q} = {name}" for q, name in result["joints"].items()) + ".", ""]
    lines += ["## Stages", "",
              "Spot distance (mm) between measured and predicted spots: on the calibration poses, held out "
              "(each pose predicted by the fit on the other folds) and on the test poses.", "",
              "| stage | model | parameters | cal RMS | CV RMS | test mean | test RMS | test max | BIC |",
              "|---|---|---|---|---|---|---|---|---|"]
    for k, s in enumerate(result["stages"]):
        lines.append(f"| {k} | {s['model']} | {s['parameters']} | {_stat(s['cal'], 'rms_mm')} | "
                     f"{_stat(s['cv'], 'rms_mm')} | {_stat(s['test'], 'mean_mm')} | {_stat(s['test'], 'rms_mm')} | "
                     f"{_stat(s['test'], 'max_mm')} | {s['bic']:.1f} |")
    if result.get("heldout_nested"):
        lines += ["", f"Held out with the selection inside the folds (the whole procedure redone on each "
                      f"training part): RMS {result['heldout_nested']['rms_mm']:.3f} mm; the CV column above "
                      "chose its effects on all the poses."]
    lines += ["", f"![stages]({plots['stages']})", "", "## Effects", ""]
    if not result["effects"]:
        lines.append("None added.")
    else:
        lines += ["| effect | where | parameter | value | std | unit | note |", "|---|---|---|---|---|---|---|"]
        for e in result["effects"]:
            where = e["where"] + (f" with {e['covariate']}" if "covariate" in e else "")
            for p in e["parameters"]:
                value = "-" if p["value"] is None else f"{p['value']:.4g}"
                std = "-" if p["std"] is None else f"{p['std']:.2g}"
                lines.append(f"| {e['title']} | {where} | {p['name']} | {value} | {std} | {p['unit']} | "
                             f"{p.get('note', '')} |")
        for e in result["effects"]:
            if "known_over_m" in e:
                (y0, y1), (z0, z1) = e["known_over_m"]["y"], e["known_over_m"]["z"]
                lines.append(f"\nThe screen's surface is known over the box of the calibration spots (y {y0:.3f} to "
                             f"{y1:.3f} m, z {z0:.3f} to {z1:.3f} m); a spot beyond it is predicted by extrapolation, "
                             "which grazing beams multiply.")
            if e["indistinguishable_from"]:
                lines.append(f"\n{e['group']} (held-out error not significantly different): neither is named "
                             f"the cause; the figures use {e['name']} ({e['where']}), the lowest BIC.")
    lines += _detector_lines(result)
    lines += ["", "## Residual against the deciding covariate", ""]
    if "residual" in plots:
        lines += [f"Before (geometric fit) and after (final model): {plots['residual_caption']}.", "",
                  f"![residual]({plots['residual']})", ""]
    lines += ["## Selection", "", "Per round, the candidates ranked by linearised held-out chi^2 per value; the "
              "shortlisted were fitted and cross-validated (rule in diagnosis.py).", ""]
    for k, ranking in enumerate(result["selection"]):
        lines += [f"Round {k + 1}:", "", "| candidate | linear CV chi^2/value | CV RMS (mm) | p fit | p held-out | "
                  "ΔBIC | outcome |", "|---|---|---|---|---|---|---|"]
        for r in ranking[:6]:
            fitted = r["cv_rms_mm"] is not None
            lines.append(f"| {r['label']} | {r['linear_cv_chi2']:.3f} | "
                         f"{r['cv_rms_mm']:.3f} | {r['p_fit']:.2g} | {r['p_heldout']:.2g} | {r['delta_bic']:.1f} | "
                         f"{r['outcome']} |" if fitted else
                         f"| {r['label']} | {r['linear_cv_chi2']:.3f} | - | - | - | - | {r['outcome']} |")
        lines.append("")
    lines += ["## Structure tests of the final residual", "", "| response | covariate | F | dof | p (adjusted) | eta^2 |",
              "|---|---|---|---|---|---|"]
    for t in diagnosis.after.tests[:8]:
        lines.append(f"| {t.response} | {t.covariate} | {t.f:.3g} | {t.dof[0]}, {t.dof[1]} | {t.p_adjusted:.2g} | "
                     f"{t.eta2:.2f} |")
    lines += ["", "## Specification of the chosen form", "",
              "Does a parameter of the final model vary with a covariate (varying-coefficient F test, "
              "diagnosis/specification.py; p weighted-Bonferroni-adjusted over every parameter and covariate):", "",
              "| parameter | covariate | F | dof | p (adjusted) | share of the residual |", "|---|---|---|---|---|---|"]
    for v in diagnosis.specification[:8]:
        lines.append(f"| {v.parameter} | {v.covariate} | {v.f:.3g} | {v.dof[0]}, {v.dof[1]} | {v.p_adjusted:.2g} | "
                     f"{100 * v.share:.1f} % |")
    return "\n".join(lines) + "\n"


def _detector_lines(result: dict) -> list[str]:
    """The flexible detector's finding and the learned compensator, apart from the physical effects."""
    found, kept = result.get("detector"), result.get("compensator")
    if found is None:
        return []
    lines = ["", "## Flexible detector", "",
             f"Held-out gain {100 * found['heldout_gain']:.1f} % of the whitened residual sum of squares "
             f"(permutation p = {found['p']:.2g}; 99 % of permuted gains below {100 * found['null_99']:.1f} %)."]
    if found["importance"] and found["heldout_gain"] > 0:
        lines += ["", "| input | MSE increase when permuted | std |", "|---|---|---|"]
        lines += [f"| {i['input']} | {i['mse_increase']:.3g} | {i['std']:.2g} |" for i in found["importance"][:6]]
    lines += ["", "## Learned compensator", ""]
    if kept is None:
        lines.append("Not kept: the detector found no significant held-out gain.")
    else:
        test = kept["test"]
        lines.append(f"Kept (compensator.json): held-out gain {100 * kept['heldout_gain']:.1f} %"
                     + (f"; test RMS with it {test['rms_mm']:.3f} mm" if test else "")
                     + ". It is not a physical effect: the effects above are the model; this only corrects what "
                       "they leave.")
    return lines


def write_report(diagnosis: Diagnosis, result: dict, out: Path) -> None:
    """report.md with residual.png and stages.png in ``out``."""
    plots = {"stages": "stages.png"}
    plot_stages(result["stages"], out / "stages.png")
    test = deciding_test(diagnosis)
    if test is not None:
        plot_residual(diagnosis, test, out / "residual.png")
        plots["residual"] = "residual.png"
        plots["residual_caption"] = f"{test.response} against {test.covariate}"
    (out / "report.md").write_text(markdown(diagnosis, result, plots))
