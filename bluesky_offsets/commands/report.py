"""One self-contained HTML report per analysis: images inlined, openable offline."""

from __future__ import annotations

import base64
import html
import json
import math
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np


def _img(path: Path, alt: str) -> str:
    data = base64.b64encode(Path(path).read_bytes()).decode()
    return f'<figure><img alt="{html.escape(alt)}" src="data:image/png;base64,{data}"/>' \
           f"<figcaption>{html.escape(alt)}</figcaption></figure>"


def _table(rows: Sequence[Mapping], columns: Sequence[str] | None = None, fmt: str = "{:.4g}") -> str:
    if not rows:
        return "<p>(none)</p>"
    columns = list(columns or rows[0].keys())

    def cell(v):
        if isinstance(v, float):
            return fmt.format(v)
        if isinstance(v, (dict, list)):
            return html.escape(json.dumps(v, default=str)[:200])
        return html.escape(str(v))

    head = "".join(f"<th>{html.escape(c)}</th>" for c in columns)
    body = "".join("<tr>" + "".join(f"<td>{cell(r.get(c, ''))}</td>" for c in columns) + "</tr>" for r in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


_CSS = """
body{font-family:system-ui,sans-serif;max-width:1200px;margin:2em auto;padding:0 1em;color:#222}
h1{font-size:1.6em}h2{font-size:1.25em;border-bottom:1px solid #ddd;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;font-size:.9em;margin:.6em 0}td,th{border:1px solid #ccc;padding:.25em .6em;
text-align:right}th{background:#f3f3f3}td:first-child,th:first-child{text-align:left}
figure{margin:1em 0}img{max-width:100%}figcaption{font-size:.85em;color:#555}
.verdict{font-size:1.15em;padding:.6em 1em;background:#eef6ee;border-left:4px solid #3a3}
.warn{background:#fff5e6;border-left-color:#e90}code{background:#f5f5f5;padding:0 .2em}
"""


def write_report(path: str | Path, *, title: str, sections: Sequence[tuple[str, str]]) -> Path:
    """Write a report from ``(heading, html body)`` sections."""
    path = Path(path)
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>",
             f"<style>{_CSS}</style></head><body><h1>{html.escape(title)}</h1>",
             f"<p>Generated {time.strftime('%Y-%m-%d %H:%M:%S')} by bluesky-offsets.</p>"]
    for heading, body in sections:
        parts.append(f"<h2>{html.escape(heading)}</h2>{body}")
    parts.append("</body></html>")
    path.write_text("\n".join(parts), encoding="utf-8")
    return path


def image(path: Path, alt: str) -> str:
    """The PNG at ``path`` as an inlined (base64) HTML figure, ``alt`` its alternative text and caption."""
    return _img(path, alt)


def table(rows, columns=None, fmt: str = "{:.4g}") -> str:
    """``rows`` (mappings) as an HTML table of ``columns`` (default: the first row's keys), floats in ``fmt``."""
    return _table(rows, columns, fmt)


def verdict(text: str, warn: bool = False) -> str:
    """``text`` as the report's highlighted verdict paragraph, in the warning colour when ``warn``."""
    return f"<p class='verdict{' warn' if warn else ''}'>{html.escape(text)}</p>"


def pre(text: str) -> str:
    """``text`` as a preformatted HTML block, escaped."""
    return f"<pre>{html.escape(text)}</pre>"


def paragraph(text: str) -> str:
    """``text`` as an HTML paragraph, escaped."""
    return f"<p>{html.escape(text)}</p>"


# --------------------------------------------------------------------------- #
# the model-vs-measurement analysis
# --------------------------------------------------------------------------- #
def _fmt_values(values: Mapping, sigma: Mapping | None = None, units: Mapping | None = None) -> str:
    parts = []
    for k, v in values.items():
        s = f"{k} = {v:.4g}"
        if sigma and k in sigma and np.isfinite(sigma[k]):
            s += f" ± {sigma[k]:.2g}"
        if units and units.get(k):
            s += f" {units[k]}"
        parts.append(s)
    return ", ".join(parts)


def _plot_progress(runs: Sequence[tuple[str, Sequence[Mapping]]], path: Path) -> Path:
    """chi2/dof of the twin at each refinement iteration (accepted steps filled)."""
    from bluesky_offsets.plotting import pyplot, save_figure
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 3.5), constrained_layout=True)
    offset = 0
    for k, (label, hist) in enumerate(runs):
        it = np.arange(len(hist)) + offset
        chi = np.array([h["chi2_reduced"] for h in hist], float)
        acc = np.array([bool(h.get("accepted", True)) for h in hist])
        ax.plot(it, chi, "-", color=f"C{k}", lw=0.8)
        ax.plot(it[acc], chi[acc], "o", color=f"C{k}", label=f"{label} (accepted)")
        ax.plot(it[~acc], chi[~acc], "x", color=f"C{k}", label=f"{label} (rejected)" if (~acc).any() else None)
        offset += len(hist)
    ax.axhline(1.0, color="k", ls="--", lw=0.8, label="noise level")
    ax.set_yscale("log")
    ax.set_xlabel("twin evaluation (iteration)")
    ax.set_ylabel("χ² / dof of the twin")
    ax.legend(fontsize=7)
    return save_figure(fig, path, dpi=100, title="fits through the twin")


def analysis_sections(analysis, spec, work: Path, *, truth: Mapping | None = None,
                      table=None, validation=None) -> list[tuple[str, str]]:
    """Report sections of a model-vs-measurement analysis (:class:`plans.diagnose.Analysis`).

    ``truth`` (simulations only) adds the hidden effect beside the fitted one; ``validation``
    (:class:`plans.design.Validation`) joins the verdict where it failed.
    """
    from bluesky_offsets.physics.parameters import METRIXS
    table = table or METRIXS
    work = Path(work)
    work.mkdir(parents=True, exist_ok=True)
    # verdict and the error history first: what people come for
    secs = [("Error history across model versions", _history_section(analysis, work, validation))]
    if analysis.refits:
        secs.append(("Fitted effect magnitudes", _effects_section(analysis, truth)))
    secs += _ranking_sections(analysis, work)
    secs.append(("Where the model fails", _failures_section(analysis, spec, work)))
    fits = _fits_section(analysis, work)
    if fits:
        secs.append(("Fits through the differentiable twin", fits))
    secs.append(("Offsets of the final model", offsets_section(analysis, table)))
    return secs


def _history_section(analysis, work: Path, validation=None) -> str:
    """The verdict (the validation's failure joined), and χ²/dof and MSE of each model version against the noise."""
    from bluesky_offsets.model.diagnosis import plot_error_history
    from plans.design import stated_verdict
    meas, comps = analysis.measurement, analysis.comparisons
    last = analysis.rankings[-1].diagnosis if analysis.rankings else None
    head = []
    if last is not None:
        failed = validation is not None and not validation.passed
        head.append(verdict(stated_verdict(analysis, validation),
                            warn=failed or (not analysis.refits and last.best is None and not last.within_noise)))
    rows = []
    for i, c in enumerate(comps):
        r = c.total_row()
        rows.append({"version": i, "model": r["model"], "χ²/dof": r["chi2_reduced"], "χ²": r["chi2"],
                     "dof (expected χ²)": r["dof"], "MSE": r["mse"], "MSE expected (noise)": r["expected_mse"],
                     "MSE / noise": r["mse_over_noise"], "configs beyond noise": f"{r['beyond_noise']} / {meas.n}",
                     "within noise": "yes" if r["within_noise"] else "no",
                     "effects": _fmt_values({f"{e}.{k}": v for e, vals in c.state.effects.items()
                                             for k, v in vals.items()},
                                            {f"{e}.{k}": v for e, vals in c.effect_sigma.items()
                                             for k, v in vals.items()}) or "—"})
    fig = plot_error_history([c.version() for c in comps], work / "error_history.png")
    head.append(table_(rows))
    head.append(image(fig, "error history: χ²/dof and MSE relative to the noise expectation, per model version"))
    return "".join(head)


def _effects_section(analysis, truth: Mapping | None) -> str:
    """The added effects' fitted magnitudes (beside the hidden ones in a simulation), their retests."""
    from bluesky_offsets.physics.effects import get as get_effect
    rows = []
    for eff, mags in analysis.magnitudes().items():
        units = {p.name: p.unit for p in get_effect(eff).parameters}
        for k, (v, s_) in mags.items():
            row = {"effect": eff, "parameter": k, "fitted": v, "± (1σ)": s_, "unit": units.get(k, "")}
            if truth is not None and eff in truth:
                hv = truth[eff].get(k)
                if hv is not None:
                    row["hidden (simulation)"] = float(hv)
                    row["error"] = f"{(v - hv) / hv * 100:+.1f} %" if hv else "—"
                    row["error / σ"] = (v - hv) / s_ if s_ > 0 else float("nan")
            rows.append(row)
    body = table_(rows)
    if truth is not None:
        body += paragraph("Hidden effects of the simulation (revealed for the demo only): "
                          + (", ".join(f"{e}: {_fmt_values(v)}" for e, v in truth.items()) or "none"))
    if analysis.retests:
        body += paragraph("Each added effect tested with the others in (the rest refitted without it, both "
                          "traced with fresh rays): kept when the model without it is beyond noise and its "
                          "Δχ² exceeds its price p ln N × dispersion.")
        body += table_([{"effect": t["effect"], "Δχ² it buys": t["gain"], "price": t["price"],
                         "χ²/dof without": t["chi2_reduced_without"],
                         "kept": "yes" if t["kept"] else ("dropped" if t["effect"] == analysis.dropped else "no")}
                        for t in analysis.retests])
    if analysis.refit_limits:
        body += limits_section("With the last effect added the model is within noise.", analysis.refit_limits)
    return body


def _ranking_sections(analysis, work: Path) -> list[tuple[str, str]]:
    """One section per diagnosis: the candidates' scores and the residual signature they explain."""
    from bluesky_offsets.model.diagnosis import plot_ranking
    secs: list[tuple[str, str]] = []
    for k_rank, rk in enumerate(analysis.rankings, 1):
        diag = rk.diagnosis
        fig = plot_ranking(diag, work / f"ranking_{k_rank}.png")
        rows = []
        for i, c in enumerate(diag.candidates, 1):
            rows.append({"rank": i, "effect": c.name, "score": c.score,
                         "twin Δχ² (bins)": c.delta_chi2_twin if c.refined else "—",
                         "÷ dispersion": c.dispersion if c.refined else "—", "price p ln N": c.penalty,
                         "fit Δχ²": c.delta_chi2_all, "held-out Δχ²": c.delta_chi2_heldout,
                         "held-out folds better / worse": f"{c.folds_improved} / {c.folds_worse} of {c.folds_total}",
                         "significant": "yes" if c.significant else "no",
                         "offsets mimic": f"{100 * c.absorbed:.0f} %" if np.isfinite(c.absorbed) else "—",
                         "value (diagnosis)": _fmt_values(c.values, c.sigma) if c.fitted
                         else f"screened only: {_fmt_values(c.values)}"})
        keys = [k for k in diag.observed_signature if not k.endswith("skewness")]
        sig_rows = [{"signature": k, "observed": diag.observed_signature[k],
                     **{c.name: c.predicted_signature.get(k, float("nan")) for c in diag.candidates[:4]}}
                    for k in keys]
        mf = diag.base_misfit
        body = (paragraph("Each candidate is fitted with the offsets through the differentiable twin (exact "
                          "Jacobians; beam features, then bins), from starting values spread over its prior range "
                          "(or, with screening, only the best after a first look at every start), beside an "
                          "offsets-only fit on the same rays, refitted from where the best candidate fits left the "
                          "offsets; held-out: each fit re-solved without each of "
                          f"{diag.folds} folds of configurations and scored on them. The best candidates are verified "
                          "in the histogram bins with fresh rays against the offsets-only "
                          "reference; score = that χ² gain ÷ the reference's χ² per degree of freedom (when > 1) − "
                          "p ln N. Significant: score above zero, and the held-out folds do not contradict it. "
                          "Base model: χ²/dof "
                          f"{mf.chi2_reduced_total:.3g} (noise: 1 ± {np.sqrt(2 / max(mf.dof_total, 1)):.2g}); "
                          f"{diag.n_traces} traces.")
                + table_(rows) + image(fig, "candidate scores; predicted residual signature of the top candidates "
                                            "beside the observed one (what the data lack)")
                + paragraph("Residual signature (model − measurement, mean over configurations) observed after the "
                            "offsets, and what each of the top candidates predicts:")
                + table_(sig_rows))
        if diag.notes:
            body += paragraph("; ".join(diag.notes))
        if diag.limits:
            body += limits_section("The model is within noise, so no candidate was fitted.", diag.limits)
        title = "Which effect is missing: ranking" + (f" (diagnosis {k_rank}, model '{diag_label(analysis, k_rank)}')"
                                                      if len(analysis.rankings) > 1 else "")
        secs.append((title, body))
    return secs


def _failures_section(analysis, spec, work: Path) -> str:
    """Overlays and residual maps of the offsets-only and the final model; misfit per configuration."""
    from bluesky_offsets.model.misfit import plot_overlays, plot_residual_maps
    meas, comps = analysis.measurement, analysis.comparisons
    body = []
    for c in ([comps[1]] if len(comps) > 2 else []) + [comps[-1]]:
        tag = c.label.replace(" ", "_").replace("+", "plus")
        ov = plot_overlays(meas.hist_x, meas.hist_y, c.model_x, c.model_y, spec, work / f"overlay_{tag}.png",
                           c.misfit, title=f"measured vs. model '{c.label}'")
        rm = plot_residual_maps(c.misfit, spec, work / f"residuals_{tag}.png",
                                title=f"pulls (measured − model) / σ, model '{c.label}'")
        body.append(f"<h3>{html.escape(c.label)}</h3>")
        body.append(image(ov, f"per configuration: measured and modelled histograms, residuals ('{c.label}')"))
        body.append(image(rm, f"per-bin residual maps across configurations ('{c.label}')"))
        if c.failing:
            body.append(paragraph(f"{len(c.failing)} (configuration, axis) regions beyond 3σ; the largest:"))
            top = sorted(c.failing, key=lambda f: -abs(f["max_pull"]))[:8]
            body.append(table_([{"config": f["configuration"], "axis": f["axis"],
                                 "range [mm]": f"{f['range_mm'][0]:+.2f} … {f['range_mm'][1]:+.2f}",
                                 "max pull": f["max_pull"], "χ² share": f["chi2_share"]} for f in top]))
        if c.correlations:
            body.append(paragraph("Strongest correlations of the residual signature with the beamline parameters "
                                  "across configurations:"))
            body.append(table_([{"signature": s, "parameter": p, "r": r} for s, p, r in c.correlations]))
    per = []
    for i in range(meas.n):
        row: dict[str, Any] = {"config": i}
        for c in comps:
            row[f"χ²/dof {c.label}"] = float(c.misfit.chi2_reduced[i])
        row["MSE expected"] = float(comps[-1].misfit.expected_mse[i])
        row[f"MSE {comps[-1].label}"] = float(comps[-1].misfit.mse[i])
        per.append(row)
    body.append(paragraph("Misfit per configuration and model version (a correct model: χ²/dof ≈ 1):"))
    body.append(table_(per))
    return "".join(body)


def _fits_section(analysis, work: Path) -> str:
    """χ²/dof along each fit through the twin; empty when nothing was fitted."""
    runs = []
    if analysis.refinement is not None:
        runs.append(("offsets", analysis.refinement.result.history))
    for rf in analysis.refits:
        if rf.history:
            runs.append((f"+ {rf.effect}", rf.history))
    if not runs:
        return ""
    fig = _plot_progress(runs, work / "fit_progress.png")
    return image(fig, "χ²/dof at each iteration (features, profiles, bins: each on its own scale)")


def design_section(designed) -> str:
    """The designed measurement's batches (:class:`plans.design.Designed`): what each chose and why."""
    rows = [{"batch": r["step"] + 1, "frames before": r["frames_before"], "frames": r["frames"],
             "criterion": f"{r['criterion']}: {r['criterion_before']:.1f} → {r['criterion_after']:.1f}",
             "candidates kept / drawn": f"{r['allowed']} / {r['candidates']}",
             "determined before → predicted after": f"{r['measured_determined']} → {r['predicted_determined']}",
             "seconds": f"{r['seconds']:.1f}"} for r in designed.steps]
    return (paragraph(f"{designed.frames} frames in all: {designed.beam.frames} to find the beam, then "
                      f"{designed.measurement.n} chosen batch by batch for what they tell about the offsets (the "
                      "twin's exact Jacobian at the current estimate; only settings whose beam stays on the screen "
                      "under the posterior), the offsets refitted between batches.")
            + (table_(rows) if rows else paragraph("no batch was designed")))


def validation_section(validation) -> str:
    """The calibrated model on frames no fit used (:class:`plans.design.Validation`)."""
    v = validation.summary()
    return (verdict(validation.line(), warn=not validation.passed)
            + table_([{"frames": v["configurations"], "chi2/dof": f"{v['chi2_reduced']:.2f}",
                       "MSE / noise": f"{v['mse_over_noise']:.2f}", "limit": f"{v['limit']:g}",
                       "run uid": v["uid"] or ""}]))


def offsets_section(model, table) -> str:
    """Each offset of the calibrated ``model`` as value ± σ with its class and the offsets it trades with.

    The numbers are the model's :class:`bluesky_offsets.model.posterior.Posterior`.
    """
    from bluesky_offsets.model.posterior import PRIOR_SIGMA, Posterior
    post = Posterior.of(model, table)
    if post is None:
        return paragraph("The final model has no covariance: its offsets are not reported without their "
                         "uncertainty.")
    c = post.counts()
    head = paragraph(f"{c['determined']} offsets determined (σ below a tenth of the prior's, the prior uniform "
                     f"within ±20 % of each range), {c['weak']} weak, {c['undetermined']} undetermined (σ above half "
                     "the prior's: the data barely beat it). σ after compensation by all other offsets; "
                     "'trades with': the offsets most correlated with it in the posterior."
                     + (f" The values and σ are under the offsets' spread the data prefer, σ "
                        f"{post.prior_sigma:.3g} of each range (the table's prior: {PRIOR_SIGMA:.3g}); the classes "
                        "against the table's prior." if post.prior_sigma != PRIOR_SIGMA else ""))
    combos = ""
    if post.combinations:
        combos = paragraph("Combinations the data determine though their parts may not be:") + table_(
            [{"σ (of the ranges)": f"{d['sigma']:.3g}",
              "combination": " ".join(f"{w:+.2f} × {n}" for n, w in d["components"])} for d in post.combinations])
    return head + table_(post.rows()) + combos


def table_(rows, columns=None, fmt: str = "{:.4g}") -> str:
    """The same as :func:`table`, under a name that a parameter ``table`` does not shadow."""
    return _table(rows, columns, fmt)


def limits_section(why: str, limits: Mapping[str, Mapping[str, float]]) -> str:
    """What a model within noise cannot exclude, after ``why`` it is within noise: a paragraph and a table.

    The limits are those of :func:`bluesky_offsets.model.diagnosis.detection_limits`.
    """
    from bluesky_offsets.model.diagnosis import limit_text
    return (paragraph(f"{why} What that cannot exclude: how large each candidate could be and still be absorbed "
                      "by the offsets, the model staying within noise (linearised at the candidate's starting "
                      "values; more can hide where the twin responds less, as a defocus near its focus):")
            + table_([{"effect": name, "parameter": q, "could hide": limit_text(name, q, lim)}
                      for name, d in limits.items() for q, lim in d.items()]))


def uid_section(uids: Mapping[str, str], store_location: str | None = None) -> str:
    """The runs' uids by step as a table, and the Python lines that load them back from the store."""
    rows = [{"step": k, "run uid": v} for k, v in uids.items() if v]
    body = table_(rows)
    loc = f'"{store_location}"' if store_location else ""
    first = next((v for v in uids.values() if v), "UID")
    body += pre("from bluesky_offsets.store import open_store\n"
                "from plans.diagnose import load_results\n"
                f"store = open_store({loc})\n"
                f'run = store["{first}"]          # the tiled node: run.metadata["start"], run["primary"].read()\n'
                f'res = load_results(store, "{first}")   # every stream as rows of plain values')
    return body


def write_analysis_report(path: str | Path, analysis, spec, *, title: str = "model vs. measurement",
                          intro: Sequence[tuple[str, str]] = (), truth: Mapping | None = None,
                          uids: Mapping[str, str] | None = None, store_location: str | None = None,
                          extra: Sequence[tuple[str, str]] = (), table=None, validation=None) -> Path:
    """Write one self-contained HTML report of an analysis; it opens offline.

    The analysis is of the beamline ``table`` names (default METRIXS); the report has its figures
    inlined (base64 PNG), tables, ranking, error history and run uids; ``validation`` joins the
    verdict where it failed.
    """
    import tempfile
    with tempfile.TemporaryDirectory(prefix="bluesky-offsets-report-") as tmp:
        secs = [*intro, *analysis_sections(analysis, spec, Path(tmp), truth=truth, table=table,
                                           validation=validation), *extra]
        secs.append(("Runs in the store", uid_section(uids if uids is not None else analysis.uids, store_location)))
        return write_report(path, title=title, sections=secs)


def diag_label(analysis, k: int) -> str:
    """The model version diagnosis ``k`` (1-based) looked at: the offsets fit, then each refit."""
    if k == 1:
        return analysis.refinement.comparison.label if analysis.refinement else analysis.comparisons[0].label
    return analysis.refits[k - 2].comparison.label


def history_lines(analysis) -> list[str]:
    """The error history of an analysis as aligned text lines: the terminal's version of the report's table.

    An uncertainty that is not finite is left out.
    """
    lines = [f"  {'model':26s} {'chi2/dof':>9s} {'MSE':>10s} {'noise MSE':>10s} {'MSE/noise':>9s}  effects"]
    for c in analysis.comparisons:
        r = c.total_row()
        eff = "; ".join(f"{e}: " + ", ".join(_value(k, v, c.effect_sigma.get(e, {}).get(k, math.nan), e)
                                              for k, v in vals.items()) for e, vals in c.state.effects.items())
        lines.append(f"  {c.label:26s} {r['chi2_reduced']:9.3f} {r['mse']:10.3e} {r['expected_mse']:10.3e} "
                     f"{r['mse_over_noise']:9.2f}  {eff}")
    return lines


def _value(name: str, value: float, sigma: float, effect: str | None = None) -> str:
    from bluesky_offsets.physics.effects import at_bound
    bound = effect is not None and at_bound(effect, name, value)
    return f"{name} = {value:.3g}" + (f" ± {sigma:.2g}" if math.isfinite(sigma) else "") + \
        (" at its prior bound" if bound else "")


def beam_section(result, work: Path, *, best=None) -> str:
    """The optimized beam (:class:`plans.optimize.BeamResult`): footprints and a table of their sizes.

    The footprints before, after and as predicted, each axis zoomed to its light; ``best``: the
    hidden true beamline's best, a simulation's check, as a :class:`~bluesky_offsets.optimize.Focus`.
    """
    import matplotlib
    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from bluesky_offsets.physics.twin import CAMERA

    prof = result.profiles
    centers = {"x": CAMERA.centers_x, "y": CAMERA.centers_y}
    # each move's frames beside its own prediction (profiles "after", "after 2", ...), zoomed to them
    rows: list[tuple[str, tuple[tuple[str, str], ...], Any]] = [("before", (("before", "before"),), result.before)]
    for k, step in enumerate(result.steps):
        tag = "" if k == 0 else f" {k + 1}"
        name = "after" if len(result.steps) == 1 else f"after ({k + 1})"
        rows.append((name, ((f"after{tag}", "measured"), (f"predicted{tag}", "predicted")), step.after))
    fig, axes = plt.subplots(len(rows), 2, figsize=(10, 3 * len(rows)), squeeze=False)
    for r, (label, keys, focus) in enumerate(rows):
        for c, axis in enumerate("xy"):
            ax = axes[r, c]
            centre, width = getattr(focus, axis), getattr(focus, f"rms_{axis}")
            for key, shown in keys:
                if prof.get(key) is None:
                    continue
                h = prof[key][c]
                ax.step(centers[axis] * 1e3, h, where="mid", lw=1.2 if shown != "predicted" else 1.0,
                        ls="-" if shown != "predicted" else "--", label=shown)
            if np.isfinite(centre) and np.isfinite(width):
                half = max(6 * width, 10 * (centers[axis][1] - centers[axis][0]))
                ax.set_xlim((centre - half) * 1e3, (centre + half) * 1e3)
            ax.set_xlabel(f"{axis} [µm]")
            ax.set_title(f"{label}: {axis} rms {width * 1e3:.1f} µm")
            ax.legend(fontsize=8)
    fig.suptitle(f"{result.optimum.target.name}: footprints at the camera's resolution")
    fig.tight_layout()
    path = Path(work) / "beam.png"
    fig.savefig(path, dpi=90)
    plt.close(fig)
    tab = [{"beam": "before (measured)", **_sizes(result.before)}]
    for k, s in enumerate(result.steps):
        tag = "" if len(result.steps) == 1 else f" {k + 1}"
        o = s.optimum
        tab.append({"beam": f"predicted{tag}", **_sizes(o.predicted),
                    "± rms x [µm]": o.sigma["x"] * 1e3, "± rms y [µm]": o.sigma["y"] * 1e3,
                    "trusted": "yes" if o.trusted else "no"})
        tab.append({"beam": f"after{tag} (measured{'; ' + s.note if s.note else ''})", **_sizes(s.after)})
    if best is not None:
        tab.append({"beam": "hidden true beamline's best (same optimizer)", **_sizes(best)})
    o = result.optimum
    moved = ", ".join(o.moved) or "nothing"
    flags = "".join(f"<li>{html.escape(f.text())}</li>" for f in o.flags[:6])
    return (_img(path, "footprints before and after the move, and as the calibrated twin predicted")
            + table(tab, fmt="{:.4g}") + paragraph(f"Moved: {moved}. At a limit: {', '.join(o.at_limit) or 'none'}. "
                                                   f"Run {result.uid}.")
            + (f"<p>Largest shares of the prediction's uncertainty:</p><ul>{flags}</ul>" if flags else ""))


def _sizes(f) -> dict:
    return {"rms x [µm]": f.rms_x * 1e3, "rms y [µm]": f.rms_y * 1e3, "FWHM x [µm]": f.fwhm_x * 1e3,
            "FWHM y [µm]": f.fwhm_y * 1e3, "intensity": f.intensity}
