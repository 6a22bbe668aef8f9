"""Outlying poses, in one place: the statistics, the identification's policy and the diagnosis's screen.

* :mod:`bayescal.outliers.stats`: the per-pose test (studentised deleted
  residuals, Sidak over the poses, Cook's distance) and the robust IRLS
  weights; its names are importable from this package.
* :mod:`bayescal.outliers.handling`: what ``identify`` does with the poses
  the test flags (``--robust``: refit by IRLS, or a robust MAP pass whose
  weights the costly methods reuse).
* :mod:`bayescal.outliers.joint`: the test of a joint geometry-plus-discrepancy
  fit, and that fit redone without the poses it names (the fit passed in).
* :mod:`bayescal.outliers.screen`: the diagnosis's screen, which takes gross
  poses out of every fit before looking for physics, and retests them
  against the final model.

See docs/outliers.md.
"""

from .stats import (
    ALPHA,
    DEFAULT_NU,
    EXCLUDE_FACTOR,
    LOSSES,
    MAX_FRACTION,
    Irls,
    PoseTest,
    describe_loss,
    exclusion_weights,
    irls_weights,
    loss_weights,
    pose_test,
    pose_test_linear,
    recording_lines,
    weighted_model,
)

__all__ = [
    "ALPHA", "DEFAULT_NU", "EXCLUDE_FACTOR", "LOSSES", "MAX_FRACTION", "Irls", "PoseTest", "describe_loss",
    "exclusion_weights", "irls_weights", "loss_weights", "pose_test", "pose_test_linear", "recording_lines",
    "weighted_model",
]
