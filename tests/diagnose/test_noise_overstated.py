"""A diagnosis against a noise stated far too large says so instead of "within the instrument noise" alone."""

import json

from bayescal.cli import main
from tests.conftest import PRS3_FILE, ROOT

RECORDING = ROOT / "examples" / "prs3" / "recording.csv"


def test_noise_stated_100_times_too_large_is_reported(tmp_path, capsys):
    text = PRS3_FILE.read_text()
    assert "sigma_position = 0.005" in text and "sigma_angle    = 5.0e-5" in text
    loud = tmp_path / "loud.toml"
    loud.write_text(text.replace("sigma_position = 0.005", "sigma_position = 0.5")
                    .replace("sigma_angle    = 5.0e-5", "sigma_angle    = 5.0e-3"))
    assert main(["diagnose", str(RECORDING), "--machine", str(loud), "--json", str(tmp_path / "d.json")]) == 0
    out = capsys.readouterr().out
    d = json.loads((tmp_path / "d.json").read_text())
    over = d["noise_overstated"]
    # residuals far below a stated noise 100 times too large (the fit, held by the prior, leaves more than the
    # real noise: the residuals' own scale is well below 1, not 1/100)
    assert over is not None and over["p_value"] < 1e-3 and over["scale"] < 0.2
    assert "NOTE the stated noise is too large for these residuals" in out
    # the noise stated as it is: nothing to say
    assert main(["diagnose", str(RECORDING), "--machine", str(PRS3_FILE), "--json", str(tmp_path / "ok.json"),
                 "--quiet"]) == 0
    assert json.loads((tmp_path / "ok.json").read_text())["noise_overstated"] is None
