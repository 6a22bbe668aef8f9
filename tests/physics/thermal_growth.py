"""An independent physics simulator for tests: parts of a 3-PRS grow with temperature.

Written without bayescal's effect code: each part's growth is applied to
the machine itself, and the machine's forward kinematics (a black box)
says where the tool goes.

* Screw (the encoder counts its turns, so the commanded ``q`` is a length
  along the cold screw): fixed at its bearing ``s_i``; warm, the point the
  nut is driven to lies at ``s_i + (q_i - s_i)(1 + alpha_s dT)``.
* Links: each grows to ``l_i (1 + alpha_l dT)``, a per-pose change of the
  geometry (``chain<i>.link_length``), not of ``q``.
* Frame (optional): the rail origins move radially with the base,
  ``B_i (1 + alpha_f dT)`` about the base origin.
"""

from __future__ import annotations

import numpy as np


class PartGrowth:
    """A :class:`bayescal.simulate.PoseTransform` driven by a temperature per pose (degC, reference 20)."""

    def __init__(self, machine, temp_C, *, alpha_screw, bearing_mm, alpha_link, alpha_frame=0.0, reference_C=20.0):
        self.m = machine
        self.dT = np.asarray(temp_C, float) - reference_C
        self.a_s = 1e-6 * np.asarray(alpha_screw, float)  # 1/K
        self.s = np.asarray(bearing_mm, float)
        self.a_l = 1e-6 * np.asarray(alpha_link, float)
        self.a_f = 1e-6 * float(alpha_frame)

    def transform(self, q, theta, aux, order):
        dT = self.dT[:, None]
        q_true = self.s + (q - self.s) * (1.0 + self.a_s * dT)
        th = np.array(theta, float, copy=True)
        geom = self.m.geometry_arrays(th[0])
        names = self.m.layout.names
        for i in range(3):
            th[:, names.index(f"chain{i + 1}.link_length")] += self.a_l[i] * geom["link_length"][i] * self.dT
            for k, x in enumerate("xy"):
                th[:, names.index(f"chain{i + 1}.rail_origin.{x}")] += self.a_f * geom["rail_origin"][i, k] * self.dT
        return q_true, th
