"""mcmc with a gross pose: the sampler runs on the weights of a robust MAP pass (docs/outliers.md)."""

import csv
import json

import numpy as np

from bayescal.cli import main
from tests.conftest import PRS3_FILE, ROOT

REC = ROOT / "examples" / "prs3" / "recording.csv"


def test_mcmc_names_the_gross_pose_and_samples_the_weighted_posterior(tmp_path):
    rows = list(csv.reader(REC.read_text().splitlines()))
    rows[12][3] = repr(float(rows[12][3]) + 0.3)  # line 13
    bad = tmp_path / "gross.csv"
    with bad.open("w", newline="") as fh:
        csv.writer(fh).writerows(rows)
    out, ref = tmp_path / "m.json", tmp_path / "map.json"
    args = ["--machine", str(PRS3_FILE), "--quiet"]
    assert main(["identify", str(bad), *args, "--method", "mcmc", "--surrogate", "linear", "--steps", "300", "--json", str(out)]) == 0
    assert main(["identify", str(REC), *args, "--method", "map", "--json", str(ref)]) == 0
    ans, clean = json.loads(out.read_text()), json.loads(ref.read_text())
    assert [o["line"] for o in ans["outliers"]] == [13] and ans["outlier_handling"].startswith("down-weighted")
    free = [i for i, p in enumerate(clean["parameters"]) if p["std"] is not None]
    v = np.array([ans["parameters"][i]["value"] for i in free])
    c, s = (np.array([clean["parameters"][i][k] for i in free]) for k in ("value", "std"))
    assert np.max(np.abs(v - c) / s) < 1.0  # the posterior mean of the clean recording's MAP, within its std
