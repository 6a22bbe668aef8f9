"""The sections of each kind of report, from the result objects the commands computed.

Numbers come from each result's ``to_dict()`` (the JSON answer) wherever
the answer has them, so the report and the JSON cannot disagree.
"""

from __future__ import annotations

import numpy as np

from .context import cell, figure, section, table

__all__ = ["BUILDERS", "inputs_section"]


# ----------------------------------------------------------------------------- shared
def inputs_section(inputs: dict, machine=None) -> dict:
    """What went in: command line, files with sha256, machine, instrument sigma, versions."""
    files = table(
        ["option", "file", "sha256", "bytes"],
        [[f"--{f['option']}" if f["option"] not in ("recording",) else f["option"], f["path"],
          cell(None, text=f["sha256"], cls="hash"), f["bytes"]] for f in inputs.get("files", [])],
        caption="input files", id="input-files",
    ) if inputs.get("files") else None
    tables = [files]
    if machine is not None:
        n = machine.noise
        tables.append(table(["machine", ""], [
            ["name", machine.name], ["kind", machine.kind], ["actuators", machine.n_actuators],
            ["geometric parameters", machine.n_params],
            ["instrument sigma, position", cell(n.sigma_position, text=f"{n.sigma_position:g} mm per axis")],
            ["instrument sigma, angle", cell(n.sigma_angle, text=f"{n.sigma_angle:g} rad per component")],
            ["sigma from", "the machine file's [measurement] table" if n.given else "the documented defaults (no [measurement] table)"],
        ], caption="machine and instrument", id="machine"))
    v = inputs.get("versions", {})
    tables.append(table(["software", "version"], [[k, val] for k, val in v.items()], caption="versions", id="versions"))
    return section("Inputs", id="inputs", text=[], tables=tables, pre=inputs.get("command"))


def _status(d: dict, p: dict) -> str:
    """How the answer came by a parameter's value: held, on a bound, fixed, decided by the prior in part, or ''."""
    if p["name"] in (d.get("held") or ()):
        return "held at nominal (fix)"
    if p["name"] in (d.get("at_bound") or ()):
        lo, hi = (d.get("bounds") or {}).get(p["name"], (None, None))
        return f"on its {'lower' if lo is not None and p['value'] == lo else 'upper'} bound"
    if not p.get("estimated", p.get("identified", True)):
        return "fixed at nominal"
    return "" if p.get("identified", True) else "decided by the prior in part"


def _parameters_table(d: dict, poor=(), tolerance=None) -> dict:
    rows, classes = [], []
    for i, p in enumerate(d["parameters"]):
        flags = [s for s in (_status(d, p),) if s]
        if p["name"] in poor:
            flags.append("! std above 10 tolerances")
        tol = None if tolerance is None else float(tolerance[i])
        rows.append([p["name"], cell(p["value"]), cell(p["std"], ".3g"), p["unit"], cell(tol, ".3g"),
                     cell(None, text="; ".join(flags))])
        classes.append("fixed" if p["std"] is None else ("flag" if p["name"] in poor else ""))
    return table(["parameter", "value", "std", "unit", "tolerance", "flags"], rows,
                 caption="identified errors (actual minus nominal) with one-sigma uncertainty", id="parameters",
                 row_classes=classes)


def _correlation_section(d: dict) -> dict:
    cov = d.get("covariance")
    pairs = d.get("strong_correlations") or []
    tables = [table(["parameter a", "parameter b", "correlation"],
                    [[p["a"], p["b"], cell(p["correlation"], "+.3f")] for p in pairs],
                    caption="strongly correlated pairs (|r| >= 0.95)", id="strong-correlations")] if pairs else []
    figs = []
    if cov and cov.get("names"):
        from ..plots.report import plot_correlation

        figs.append(figure(lambda p: plot_correlation(cov["correlation"], cov["names"], p),
                           "correlation matrix of the identified parameters (full matrix in the JSON answer, key covariance)"))
    text = ["No pair of identified parameters is correlated beyond |r| = 0.95."] if not pairs else [
        f"{len(pairs)} pairs are correlated beyond |r| = 0.95: the data determine their combination better than each one."]
    return section("Correlations", id="correlations", text=text, tables=tables, figures=figs)


def _unidentifiable_section(d: dict) -> dict:
    fixed, combos = d.get("fixed") or [], d.get("unidentifiable") or []
    # free="auto" with a prior (map, ridge, tsvd, kalman, mcmc): confounded parameters are estimated, the prior
    # deciding their split (bayescal.identify.resolve_free); they are not identifiable from the data either
    prior = d.get("decided_by_prior") or []
    if not fixed and not combos and not prior:
        return section("What the measurement cannot separate", id="unidentifiable",
                       text=["Every parameter that was asked for is identifiable from these poses."])
    text, tables = [], []
    if fixed:
        text.append(f"{len(fixed)} parameters cannot be identified from these poses and were held at nominal: "
                    + ", ".join(fixed) + ".")
    if combos:
        text.append("The measurement cannot tell apart the parameters in each of these combinations "
                    "(moving along one of them changes no measured value to first order):")
        tables.append(table(["combination the data cannot see"], [[c] for c in combos], id="combinations"))
    if prior:
        text.append(f"{len(prior)} combinations are not separated by these poses and were decided by the prior "
                    "(estimated near nominal in proportion to the tolerances, not fixed; --method ls fixes them instead):")
        tables.append(table(["combination decided by the prior"], [[c] for c in prior], id="decided-by-prior"))
    return section("What the measurement cannot separate", id="unidentifiable", text=text, tables=tables)


def _outlier_indices(result) -> list[int]:
    """0-based poses the answer names as outliers: its ``outliers`` (docs/formats.md section 4: CSV ``line``, header = 1)."""
    return [int(o["line"]) - 2 for o in result.to_dict().get("outliers") or []]


def _residual_section(result, model, sigma) -> dict | None:
    after, before = result.residuals_after, result.residuals_before
    if after is None and model is not None:
        pred = model.predict(result.theta)
        after = model.residual(pred) if pred.success.all() else None
        # "before": the machine file as given (a model's theta_start: its stored effect values), else nominal
        ref = model.theta_start
        before = model.residual(model.predict(np.zeros(model.machine.n_params) if ref is None else ref))
    if after is None:
        return None
    after = np.asarray(after, float)
    # position components per row: 3 for a measured point, 1 for a distance or height (noise alone: sigma sqrt(k))
    k = min(3, after.shape[1])
    pos_a = np.linalg.norm(after[:, :3], axis=1)
    pos_b = np.linalg.norm(np.asarray(before, float)[:, :3], axis=1) if before is not None else None
    ang = np.linalg.norm(after[:, 3:], axis=1) if after.shape[1] > 3 else None
    outliers = _outlier_indices(result)
    rows, classes = [], []
    for i in range(after.shape[0]):
        r = [i + 1, cell(1e3 * pos_a[i], ".2f")]
        if pos_b is not None:
            r.insert(1, cell(1e3 * pos_b[i], ".2f"))
        if ang is not None:
            r.append(cell(ang[i], ".3e"))
        r.append(cell(None, text="outlier" if i in outliers else ""))
        rows.append(r)
        classes.append("outlier" if i in outliers else "")
    cols = ["pose"] + (["position error before (um)"] if pos_b is not None else []) + ["position error after (um)"]
    cols += (["angle error after (rad)"] if ang is not None else []) + ["mark"]
    from ..plots.report import plot_pose_residuals

    fig = figure(lambda p: plot_pose_residuals(pos_a, p, pos_before=pos_b, sigma=sigma, outliers=outliers, n_axes=k),
                 "position error per pose before and after calibration; outliers in red")
    text = [f"RMS position error after calibration {1e3 * np.sqrt(np.mean(pos_a**2)):.2f} um over {pos_a.size} poses"
            + (f"; instrument noise alone gives about {1e3 * sigma * np.sqrt(k):.2f} um." if sigma else ".")]
    if outliers:
        text.append(f"{len(outliers)} poses are marked as outliers: " + ", ".join(str(i + 1) for i in outliers) + ".")
    return section("Residuals per pose", id="residuals", text=text, figures=[fig],
                   tables=[table(cols, rows, id="pose-residuals", row_classes=classes)])


# ----------------------------------------------------------------------------- kinds
def _instrument_section(d: dict, answer_extra: dict | None) -> dict | None:
    """The fitted instrument frame, the outlier handling and the plausibility verdict of the answer."""
    extra = answer_extra or {}
    text = []
    frame = extra.get("frame")
    if frame:
        fmt = lambda v: "[" + ", ".join(f"{x:.6g}" for x in v) + "]"  # noqa: E731
        text.append(f"Instrument frame ({'fitted' if frame.get('fitted', True) else 'known'}): origin {fmt(frame['origin'])} mm, "
                    f"rotation vector {fmt(frame['rotation_vector'])} rad.")
    if d.get("outlier_handling"):
        text.append(f"Outliers: {d['outlier_handling']}.")
    if "plausible" in extra:
        pl = extra.get("plausibility") or {}
        if extra["plausible"]:
            text.append("Plausible: no machine parameter beyond 10 tolerances, residual degrees of freedom left.")
        else:
            text += ["NOT PLAUSIBLE (no calibrated machine written unless --force): " + "; ".join(pl.get("reasons", []))]
            text += ["likely cause: " + c for c in pl.get("causes", [])]
    if not text:
        return None
    return section("Instrument, outliers and plausibility", id="instrument", text=text)


def identify_sections(result, *, machine=None, model=None, choice=None, answer_extra=None, **_) -> tuple[str, list[dict]]:
    d = result.to_dict()
    method = d.get("method", result.method)
    ok = d.get("success", True)
    rb, ra = d.get("rms_before", {}), d.get("rms_after", {})
    stats = [["method", method], ["status", "succeeded" if ok else "FAILED"], ["message", d.get("message") or "-"],
             ["measurement", f"{d.get('dof')}-DOF, {d.get('n_poses')} poses"],
             ["RMS position before", cell(rb.get("position"), text=f"{1e3 * rb['position']:.3f} um") if rb.get("position") is not None else "-"],
             ["RMS position after", cell(ra.get("position"), text=f"{1e3 * ra['position']:.3f} um") if ra.get("position") is not None else "-"]]
    if rb.get("angle") is not None:
        stats.append(["RMS angle before / after", f"{rb['angle']:.3e} / {ra.get('angle') or float('nan'):.3e} rad"])
    for key, label in (("lam", "lambda"), ("k", "k"), ("chi2", "chi-square"), ("rank", "rank"), ("iterations", "iterations"),
                       ("covariance_kind", "covariance")):
        if d.get(key) is not None:
            stats.append([label, cell(d[key]) if isinstance(d[key], (int, float)) else d[key]])
    if "convergence" in d:
        for k, v in d["convergence"].items():
            stats.append([f"mcmc {k.replace('_', ' ')}", cell(v, ".4g")])
    if "poses_needed" in d:
        stats.append(["poses needed (within 10% of final accuracy)", d["poses_needed"]])
    poor, tol = result.poorly_determined(), result.tolerance
    if tol is None:
        # the answer's parameters are the model's (a ballbar model adds its pivots, a fitted frame its six):
        # the model's machine has their tolerances, the machine file's only the geometry's
        src = model.machine if model is not None else machine
        tol = None if src is None else src.tolerance
    if tol is not None and len(tol) != len(d["parameters"]):
        tol = None  # not this answer's parameters: no column rather than a wrong one
    # a machine file without a [measurement] table states no noise (its sigmas are weights): nothing to compare with
    sigma = machine.noise.sigma_position if machine is not None and machine.noise.given else None
    sections = [
        section("Fit", id="fit", tables=[table(["statistic", "value"], stats, id="fit-statistics")],
                text=[] if ok else ["The identification did not succeed: its numbers are shown for diagnosis, not for use."]),
        section("Parameters", id="parameters-section", tables=[_parameters_table(d, poor, tol)],
                text=["Flags: '! std above 10 tolerances' marks values the data do not determine (not physical errors); "
                      "'fixed at nominal' marks parameters the data cannot identify, 'held at nominal (fix)' those the "
                      "user held, 'on its lower/upper bound' those the answer put on a bound (no std: the others' is "
                      "conditional on them there), 'decided by the prior in part' those the data do not separate."]),
        _correlation_section(d),
        _unidentifiable_section(d),
        _instrument_section(d, answer_extra),
        _residual_section(result, model, sigma),
    ]
    figs = []
    if choice is not None:
        from ..plots.regularisation import plot_choice

        figs.append(figure(lambda p: plot_choice(choice, p), "regularisation rules: the chosen value and every rule's curve"))
    if method == "kalman":
        from ..plots.bayes import plot_filter_history

        figs.append(figure(lambda p: plot_filter_history(result, p), "Kalman filter: uncertainty after each pose"))
    if method == "mcmc" and ok:
        from ..plots.bayes import plot_pair, plot_trace_pages

        figs.append(figure(lambda p: plot_trace_pages(result, p.parent), "MCMC trace, one labelled row per parameter in its unit"))
        figs.append(figure(lambda p: plot_pair(result, p), "MCMC pair plot of the most uncertain parameters"))
    figs = _flatten(figs)
    if figs:
        sections.append(section(f"Figures of {method}", id="method-figures", figures=figs))
    sections.append(section("Text report", id="text-report", pre=result.report()))
    title = f"Identification of '{d.get('machine')}' ({d.get('kind')}), method {method}"
    return title, sections


def diagnose_sections(result, **_) -> tuple[str, list[dict]]:
    d = result.to_dict()
    loc = d.get("located")
    verdict = d["verdict"]
    words = {"none": "the geometric model explains the recording to within the instrument noise",
             "unexplained": "a structured mismatch remains that no effect of the library explains"}
    evidence = [
        ["verdict", cell(None, text=verdict, cls="verdict")],
        ["meaning", words.get(verdict, f"model {verdict}: it is decisive and improves the out-of-sample fit")],
        ["chi-square, geometric model", f"{d['chi2']['geometric']:.1f} for {d['chi2']['geometric_expected']:.1f} expected (p = {d['chi2']['geometric_p']:.2g})"],
        ["chi-square, final model", f"{d['chi2']['final']:.1f} for {d['chi2']['final_expected']:.1f} expected (p = {d['chi2']['final_p']:.2g})"],
        ["cross-validated position RMS", f"{1e3 * d['rms_before']:.2f} um -> {1e3 * d['rms_after']:.2f} um"],
        ["instrument noise alone", cell(d["rms_noise"], text=f"{1e3 * d['rms_noise']:.2f} um")],
        ["selected effects", ", ".join(d["selected"]) or "-"],
    ]
    if loc:
        evidence.insert(2, ["located channel", f"{loc['channel']} (distance correlation {loc['strength']:.3f}, "
                            f"Holm p = {loc['p_value']:.2g}, {'significant' if loc['significant'] else 'not significant'}) "
                            f"{loc.get('detail') or ''}"])
    eff_rows = [[e["name"], "yes" if e["detected"] else "no", cell(e["evidence"], ".1f"), cell(1e3 * e["rms_before"], ".2f"),
                 cell(1e3 * e["rms_after"], ".2f"), e.get("note", "")] for e in d["effects"]]
    eff_rows += [[s["name"], "skipped", "-", "-", "-", s["reason"]] for s in d["skipped"]]
    eff = table(["effect", "kept", "log Bayes factor (nats)", "CV RMS before (um)", "CV RMS after (um)", "note"], eff_rows,
                caption="effects tried: kept when the evidence is decisive (> ln 100) and the cross-validated RMS improves",
                id="effects")
    params = [[e["name"], p["name"], cell(p["value"], ".4g"), cell(p["std"], ".3g"), p["unit"]]
              for e in d["effects"] if e["detected"] for p in e["parameters"]]
    ch = [[c.get("channel"), cell(c.get("strength"), ".3f"), cell(c.get("p_adjusted", c.get("p_value")), ".2g"),
           "yes" if c.get("significant") else "no", c.get("detail", "")] for c in d.get("channels", [])]
    from ..plots.diagnose import plot_diagnosis

    figs = _flatten([figure(lambda p: plot_diagnosis(result, p.parent), "diagnosis figures")])
    sections = [
        section("Verdict", id="verdict", tables=[table(["", ""], evidence, id="verdict-evidence")]),
        section("Effects tried", id="effects-section", tables=[eff] + ([table(
            ["effect", "parameter", "value", "std", "unit"], params, caption="fitted parameters of the kept effects",
            id="effect-parameters")] if params else [])),
        section("Located channel", id="located", tables=[table(
            ["channel", "strength (distance correlation)", "p (Holm)", "significant", "detail"], ch, id="channels")],
            text=["Every channel's dependence of the geometric fit's residuals, strongest first."]),
        section("Figures", id="figures", figures=figs),
        section("Text report", id="text-report", pre=result.report()),
    ]
    return f"Diagnosis of {d['recording']} on '{d['machine']}': verdict {verdict}", sections


def compare_sections(result, **_) -> tuple[str, list[dict]]:
    d = result.to_dict()
    from ..plots.compare import plot_comparison

    figs = _flatten([figure(lambda p: plot_comparison(result, p.parent), "comparison")])
    from ..compare.result import _UNITS

    # the metric's own display unit, as the text report (rms_angle in urad, not the positions' um)
    unit, f = _UNITS.get(result.metric, ("", 1.0))
    summ = result.summary
    rows = [[lab, s.get("n"), s.get("failures"), cell(f * s["median"], ".4g") if s.get("median") is not None else "-",
             cell(f * s["mean"], ".4g") if s.get("mean") is not None else "-"] for lab, s in summ.items()]
    return f"Comparison of methods on '{d['config'].get('machine', '')}' ({d['n_trials']} trials)", [
        section("Summary", id="summary", tables=[table(["method", "ok", "failed", f"median {result.metric} ({unit})",
                                                        f"mean {result.metric} ({unit})"], rows, id="methods")]),
        section("Figures", id="figures", figures=figs),
        section("Text report", id="text-report", pre=result.report()),
    ]


def plan_sections(result, *, machine=None, **_) -> tuple[str, list[dict]]:
    d = result.to_dict()
    from ..plots.report import plot_plan

    units = machine.actuator_units if machine is not None else ()
    lim = machine.q_limits if machine is not None else None
    figs = [figure(lambda p: plot_plan(result.q, p, units=units, q_limits=lim), "planned poses")]
    head = [f"q{j + 1}" + (f" ({units[j]})" if j < len(units) else "") for j in range(result.q.shape[1])]
    rows = [[i + 1] + [cell(v, ".6g") for v in row] for i, row in enumerate(result.q)]
    return f"Measurement plan for '{d['machine']}': {d['n_poses']} poses, criterion {d['criterion']}", [
        section("Plan", id="plan", tables=[table(["pose_id"] + head, rows, id="poses")]),
        section("Figures", id="figures", figures=figs),
        section("Text report", id="text-report", pre=result.report()),
    ]


def grid_sections(result, *, identification=None, machine=None, **_) -> tuple[str, list[dict]]:
    d = result.to_dict()
    from ..plots.bayes import plot_grid

    stats = [[k.replace("_", " "), cell(v, ".5g") if isinstance(v, (int, float)) else str(v)]
             for k, v in d.items() if k not in ("axes", "machine")]
    sections = [
        section("Grid", id="grid", tables=[table(["", ""], stats, id="grid-summary")]),
        section("Figures", id="figures", figures=_flatten([figure(
            lambda p: plot_grid(result, p, units=machine.actuator_units if machine is not None and d.get("space") != "tool" else None),
            "grid: correction and its std")])),
        section("Text report", id="text-report", pre=result.report()),
    ]
    if identification is not None:
        idd = identification.to_dict()
        poor, tol = identification.poorly_determined(), identification.tolerance
        sections.insert(1, section("Identified parameters", id="parameters-section",
                                   tables=[_parameters_table(idd, poor, tol if tol is not None else
                                                             (machine.tolerance if machine is not None else None))]))
    return f"Compensation grid of '{d['machine']}'", sections


def compensate_sections(result, *, evaluation=None, **_) -> tuple[str, list[dict]]:
    from ..plots.report import plot_bic_grid

    rows = []
    for j, z in enumerate(result.zs):
        for i, x in enumerate(result.xs):
            rows.append([i, j, cell(float(x)), cell(float(z)), cell(float(result.error[j, i, 0])), cell(float(result.error[j, i, 1])),
                         cell(float(result.std[j, i, 0])), cell(float(result.std[j, i, 1]))])
    sections = [
        section("Grid", id="grid", text=[result.report()], tables=[table(
            ["i", "j", "x (mm)", "z (mm)", "ex (mm)", "ez (mm)", "std ex (mm)", "std ez (mm)"], rows, id="nodes")]),
        section("Figures", id="figures", figures=[figure(lambda p: plot_bic_grid(result, p), "BIC node errors")]),
    ]
    if evaluation:
        sections.insert(1, section("Evaluation on fresh points", id="evaluation", tables=[table(
            ["", "mm"], [[k.replace("_mm", "").replace("_", " "), cell(v)] for k, v in evaluation.items()], id="evaluation-table")]))
    return "Bilinear interpolation compensation grid", sections


def _flatten(figs) -> list[dict]:
    out = []
    for f in figs:
        if isinstance(f, list):
            out += f
        elif f:
            out.append(f)
    return out


BUILDERS = {
    "identify": identify_sections,
    "diagnose": diagnose_sections,
    "compare": compare_sections,
    "plan": plan_sections,
    "grid": grid_sections,
    "compensate": compensate_sections,
}
