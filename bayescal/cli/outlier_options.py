"""``identify`` options and steps for outlying poses: --robust, --nu, --outlier-alpha (docs/outliers.md)."""

from __future__ import annotations

from ..constants import DEFAULT_NU, OUTLIER_ALPHA as ALPHA

__all__ = ["add_outlier_arguments", "outlier_kwargs"]


def add_outlier_arguments(p) -> None:
    g = p.add_argument_group("outliers (docs/outliers.md)")
    g.add_argument(
        "--robust", choices=("auto", "t", "huber", "off"), default="auto",
        help="what to do with poses no model of the machine explains: 'auto' (default) tests every pose and, when "
        "the test flags any, refits by Student-t IRLS; 't' / 'huber' always refit by IRLS with that loss; "
        "'off' keeps every pose at full weight (flagged poses are still reported)",
    )
    g.add_argument(
        "--nu", type=float, default=DEFAULT_NU, help=f"degrees of freedom of the Student-t loss (default {DEFAULT_NU:g})",
    )
    g.add_argument(
        "--outlier-alpha", type=float, default=ALPHA, metavar="ALPHA",
        help=f"family-wise level of the outlier test over all poses (default {ALPHA:g})",
    )


def outlier_kwargs(args, rec, n_poses: int) -> dict:
    """Keyword arguments of :mod:`bayescal.outliers.handling` from the parsed options."""
    from ..errors import InputError
    from ..outliers import recording_lines

    if not 0 < args.outlier_alpha < 1:
        raise InputError(f"--outlier-alpha: expected a level between 0 and 1, got {args.outlier_alpha!r}")
    if not args.nu > 0:
        raise InputError(f"--nu: expected a number > 0, got {args.nu!r}")
    return {"robust": args.robust, "nu": args.nu, "alpha": args.outlier_alpha, "lines": recording_lines(n_poses, rec)}
