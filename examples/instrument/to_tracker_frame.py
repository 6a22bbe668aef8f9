"""Rewrite a recording (base frame) as a laser tracker in another frame would deliver it.

Usage: python to_tracker_frame.py IN.csv OUT.csv [--angle-deg 40] [--origin 2500,-1200,800] [--seed 0]

The tracker frame is rotated by --angle-deg about a random axis (seeded) and
its origin sits at --origin (mm) in the base frame: p_base = R p_tracker + o,
so the tracker reads p_tracker = R^T (p_base - o), orientations R^T R_base
and tool axes R^T n.  Only numpy, scipy and the csv module: independent of
bayescal, on purpose.
"""

import argparse
import csv

import numpy as np
from scipy.spatial.transform import Rotation

ap = argparse.ArgumentParser()
ap.add_argument("inp")
ap.add_argument("out")
ap.add_argument("--angle-deg", type=float, default=40.0)
ap.add_argument("--origin", default="2500,-1200,800")
ap.add_argument("--seed", type=int, default=0)
a = ap.parse_args()

axis = np.random.default_rng(a.seed).normal(size=3)
R = Rotation.from_rotvec(np.radians(a.angle_deg) * axis / np.linalg.norm(axis))
o = np.array([float(v) for v in a.origin.split(",")])
with open(a.inp, newline="") as fh:
    rows = list(csv.DictReader(fh))
for r in rows:
    p = np.array([float(r[c]) for c in ("x", "y", "z")])
    r["x"], r["y"], r["z"] = map(repr, R.inv().apply(p - o).tolist())
    if "rx" in r:
        rb = Rotation.from_rotvec([float(r[c]) for c in ("rx", "ry", "rz")])
        r["rx"], r["ry"], r["rz"] = map(repr, (R.inv() * rb).as_rotvec().tolist())
    if "nx" in r:
        n = R.inv().apply([float(r[c]) for c in ("nx", "ny", "nz")])
        r["nx"], r["ny"], r["nz"] = map(repr, n.tolist())
with open(a.out, "w", newline="") as fh:
    w = csv.DictWriter(fh, fieldnames=list(rows[0]), lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
print(f"tracker frame: origin {o.tolist()} mm, rotation vector {R.as_rotvec().tolist()} rad")
