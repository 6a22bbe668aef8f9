"""Panel titles and colours of the pose-planning figure."""

import numpy as np

from bayescal.plots.design import _panel_title


def test_panel_titles_name_the_setting_not_a_setting_followed_by_dof():
    rows = [{"dof": "prs3-6dof", "title": "3-PRS, 6-DOF measurement"}, {"dof": "delta-height"}, {"dof": 5}]
    assert _panel_title(rows, "prs3-6dof") == "3-PRS, 6-DOF measurement"
    assert _panel_title(rows, "delta-height") == "delta-height"  # never "delta-height-DOF measurement"
    assert _panel_title(rows, 5) == "5-DOF measurement"
    assert _panel_title([{"dof": np.int64(6)}], np.int64(6)) == "6-DOF measurement"


def test_a_design_has_the_same_colour_in_every_panel():
    from bayescal.plots.design import _design_colors

    rows = [{"dof": "a", "design": "planned-I"}, {"dof": "b", "design": "planned-D"},
            {"dof": "b", "design": "planned-I"}, {"dof": "a", "design": "random"}]
    c = _design_colors(rows)
    assert c["random"] == "C0" and len(set(c.values())) == 3
    # panel "a" shows planned-I alone: the colour is the one it has beside planned-D in panel "b"
    assert c == _design_colors(rows[1:] + rows[:1])
