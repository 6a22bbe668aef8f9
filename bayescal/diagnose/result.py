"""The answer of a diagnosis (docs/formats.md section 3, ``bayescal diagnose``)."""

from __future__ import annotations

from dataclasses import dataclass, field

from .locate import ChannelDependence, Location
from ..notebook import ShowsReport

__all__ = ["EffectTrial", "Diagnosis", "ParameterValue"]


@dataclass(frozen=True)
class ParameterValue:
    """One fitted effect parameter."""

    name: str
    value: float
    std: float | None
    unit: str

    def to_dict(self) -> dict:
        return {"name": self.name, "value": self.value, "std": self.std, "unit": self.unit}


@dataclass(frozen=True)
class EffectTrial:
    """One effect fitted jointly with the geometry.

    Attributes
    ----------
    name : str
    detected : bool
        Kept in the final model (decisive evidence and better out-of-sample fit).
    evidence : float
        Log Bayes factor (Laplace) in favour of adding the effect, nats.
    parameters : tuple of ParameterValue
    rms_before, rms_after : float
        Cross-validated position RMS (mm) of the geometric model without and with the effect.
    note : str
    """

    name: str
    detected: bool
    evidence: float
    parameters: tuple[ParameterValue, ...]
    rms_before: float
    rms_after: float
    note: str = ""

    def to_dict(self) -> dict:
        return {
            "name": self.name, "detected": self.detected, "evidence": self.evidence,
            "parameters": [p.to_dict() for p in self.parameters],
            "rms_before": self.rms_before, "rms_after": self.rms_after, "note": self.note,
        }


@dataclass(frozen=True)
class Diagnosis(ShowsReport):
    """What the diagnosis found.

    Attributes
    ----------
    verdict : str
        An effect name, ``"none"`` or ``"unexplained"``.
    effects : tuple of EffectTrial
        Every effect tried, most evident first.
    selected : tuple of str
        The effects of the final model, in the order they were added.
    location : Location
        Every channel's dependence; ``location.strongest`` is ``located``.
    skipped : tuple of (str, str)
        Effects not tried, and why.
    chi2_geometric, chi2_final : float
        Whitened residual sum of squares of the geometric and the final model.
    dof_geometric, dof_final : float
        Their expected values under the noise alone (rows minus effective parameters).
    p_geometric, p_final : float
        Chi-square test p-values.
    rms_cv_geometric, rms_cv_final : float
        Cross-validated position RMS, mm.
    rms_noise : float
        Position RMS of the instrument noise alone, ``sigma sqrt(3)``, mm.
    n_poses, dof : int
    machine_name, recording : str
    seed : int
    theta_final, theta_geometric : ndarray, shape (P,), or None
        Geometric errors of the final model (jointly with the selected
        effects) and of the geometric model alone.
    outliers : OutlierScreen or None
        Gross-error poses named and excluded before the diagnosis (docs/formats.md section 4).
    """

    verdict: str
    effects: tuple[EffectTrial, ...]
    selected: tuple[str, ...]
    location: Location
    skipped: tuple[tuple[str, str], ...]
    chi2_geometric: float
    chi2_final: float
    dof_geometric: float
    dof_final: float
    p_geometric: float
    p_final: float
    rms_cv_geometric: float
    rms_cv_final: float
    rms_noise: float
    n_poses: int
    dof: int
    machine_name: str
    recording: str
    seed: int
    message: str = ""
    extra: dict = field(default_factory=dict)
    #: Geometric errors (mm, rad) of the final model, fitted jointly with the selected effects, and of
    #: the geometric model alone: what ``--write-machine`` folds into the calibrated machine.
    theta_final: object = None
    theta_geometric: object = None
    #: The stated inputs of effects the diagnosis used (``effect_settings``), by effect name: written
    #: beside the fitted parameters in the calibrated machine's ``[effect.*]`` tables.
    effect_settings: dict = field(default_factory=dict)
    outliers: object = None  # OutlierScreen (bayescal.outliers.screen), None if not screened
    #: How well the written geometry (without the effects) is known and what it trades off against
    #: (bayescal.diagnose.confound.GeometryConfound); None when no effect was selected.
    confound: object = None
    #: The model discrepancy fitted where the final model still misfits (bayescal.diagnose.discrepancy.
    #: DiscrepancyTrial); None when not tried.
    discrepancy: object = None
    #: The calibration's uncertainty the written machine carries (bayescal.prediction.record.CalibrationRecord).
    record: object = None
    #: The answer's ``frame`` (or ``frames``) keys of a fitted instrument frame (docs/formats.md sections 4, 8):
    #: the geometric fit's, with its Laplace std; ``{}`` in the base frame.
    frame: dict = field(default_factory=dict)
    #: The stated noise's test on the geometric fit and the factor on the tool rows' sigma the diagnosis used
    #: (bayescal.diagnose.noise.NoiseSettling); None for a diagnosis built by hand.
    noise: object = None

    @property
    def located(self) -> ChannelDependence | None:
        return self.location.strongest

    @property
    def noise_overstated(self) -> dict | None:
        """Where the geometric fit's residuals were far smaller than the stated noise allows, the test, else None.

        ``{"p_value": P(X <= chi2), "scale": s, "reduced_chi2_stated": r}`` at
        the stated noise, ``X`` chi-square with the geometric fit's expected
        degrees of freedom, when that lower tail is below
        :data:`bayescal.identify.noise.ALPHA` and the reduced chi-square ``r``
        below :data:`bayescal.identify.noise.OVERSTATED_BELOW`; ``s`` is the
        factor on the tool rows' stated sigma that the diagnosis then ran at
        (:mod:`bayescal.diagnose.noise`: refitted until it settles).
        """
        n = self.noise
        if n is None or n.check.verdict != "overstated":
            return None
        return {"p_value": float(n.check.p_value), "scale": float(n.scale),
                "reduced_chi2_stated": float(n.check.reduced)}

    def to_dict(self) -> dict:
        """The JSON answer of docs/formats.md section 3 (plus documented extra keys), in JSON's own types.

        ``bayescal diagnose --json`` writes ``json_text`` of it (the fitted
        instrument frame's keys included when ``--frame fit``).
        """
        from ..io.answers import to_jsonable

        return to_jsonable(self._answer())

    def _answer(self) -> dict:
        loc = self.located
        return {
            "verdict": self.verdict,
            "effects": [e.to_dict() for e in self.effects],
            "located": None if loc is None else {
                "channel": loc.channel, "strength": loc.strength, "p_value": loc.p_adjusted,
                "significant": loc.significant, "detail": loc.detail,
            },
            "selected": list(self.selected),
            "skipped": [{"name": n, "reason": r} for n, r in self.skipped],
            "rms_noise": self.rms_noise,
            "rms_before": self.rms_cv_geometric,
            "rms_after": self.rms_cv_final,
            "chi2": {
                "geometric": self.chi2_geometric, "geometric_expected": self.dof_geometric, "geometric_p": self.p_geometric,
                "final": self.chi2_final, "final_expected": self.dof_final, "final_p": self.p_final,
            },
            "channels": [c.to_dict() for c in self.location.channels],
            "machine": self.machine_name,
            "recording": self.recording,
            "n_poses": self.n_poses,
            "dof": self.dof,
            "seed": self.seed,
            "evidence_kind": "log Bayes factor, Laplace approximation (nats)",
            "message": self.message,
            "noise_overstated": self.noise_overstated,
            "written_geometry": None if self.confound is None else self.confound.to_dict(),
            "discrepancy": None if self.discrepancy is None else self.discrepancy.to_dict(),
            **self._outlier_keys(),
            **self.frame,
        }

    def _outlier_keys(self) -> dict:
        """docs/formats.md section 4: ``outliers`` by CSV line and what the diagnosis did with them."""
        if self.outliers is None:
            return {"outliers": [], "outlier_handling": "not screened"}
        return self.outliers.to_dict()

    def report(self) -> str:
        """A report a calibration engineer can act on."""
        L = [f"diagnosis of {self.recording} ({self.n_poses} poses, {self.dof}-DOF) on {self.machine_name}"]
        L.append(
            f"geometric calibration: chi2 {self.chi2_geometric:.1f} for {self.dof_geometric:.1f} expected "
            f"(p = {self.p_geometric:.2g}); cross-validated position RMS {1e3 * self.rms_cv_geometric:.1f} um "
            f"(noise alone {1e3 * self.rms_noise:.1f} um)"
        )
        if self.outliers is not None:
            L.append(self.outliers.report())
        loc = self.located
        if loc is not None:
            sig = "significant" if loc.significant else "not significant"
            L.append(
                f"located: the residuals depend most on {loc.channel} (strength {loc.strength:.2f}, "
                f"Holm p = {loc.p_adjusted:.2g}, {sig}){' ' + loc.detail if loc.detail else ''}"
            )
        over = self.noise_overstated
        if over is not None:
            L.append(f"NOTE the stated noise is too large for these residuals: reduced chi-square "
                     f"{over['reduced_chi2_stated']:.3g} at the stated sigma (P(X <= chi2) = {over['p_value']:.2g}). "
                     f"The diagnosis ran at {over['scale']:.3g} x the stated tool sigma, the noise the geometric fit's "
                     "residuals show (an upper bound: they carry any mismatch too); state the instrument's noise "
                     "([measurement] sigma_position, sigma_angle) as it is")
        if self.verdict == "none":
            L.append("VERDICT none: the geometric model explains the recording to within the instrument noise.")
        elif self.verdict == "discrepancy":
            d = self.discrepancy
            L.append(
                "VERDICT discrepancy: no effect of the library explains the mismatch; a model discrepancy does, out of "
                f"sample: position RMS {1e3 * self.rms_cv_geometric:.1f} um -> {1e3 * self.rms_cv_final:.1f} um. "
                f"It resembles {d.resembles if d is not None else 'a smooth error'}."
            )
        elif self.verdict == "unexplained":
            L.append(
                "VERDICT unexplained: a structured mismatch remains that no effect of the library explains; "
                f"look at {loc.channel if loc else 'the residuals'} (residual-against-channel figures: --figures DIR)."
            )
        else:
            L.append(
                f"VERDICT {self.verdict}: model it. Out-of-sample position RMS {1e3 * self.rms_cv_geometric:.1f} um "
                f"-> {1e3 * self.rms_cv_final:.1f} um with {', '.join(self.selected)}."
            )
        if self.confound is not None:
            L.append(self.confound.report())
        L.append("")
        L.append("effect                 kept  evidence  CV RMS before -> after (um)")
        for e in self.effects:
            L.append(
                f"{e.name:<22} {'yes' if e.detected else 'no ':<4} {e.evidence:9.1f}  "
                f"{1e3 * e.rms_before:8.2f} -> {1e3 * e.rms_after:8.2f}  {e.note}"
            )
            if e.detected:
                for p in e.parameters:
                    std = "n/a" if p.std is None else f"{p.std:.3g}"
                    L.append(f"    {p.name:<24} {p.value:12.4g} +- {std:<9} {p.unit}")
        for n, r in self.skipped:
            L.append(f"{n:<22} skipped: {r}")
        if self.discrepancy is not None:
            L.append(self.discrepancy.report())
        if self.message:
            L.append(self.message)
        return "\n".join(L)
