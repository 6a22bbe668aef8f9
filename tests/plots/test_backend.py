"""Figure files are written whole or not at all, and the figure is closed either way."""

import pytest

from bayescal.plots._backend import pyplot, save


def test_save_writes_a_png_atomically_and_closes(tmp_path):
    plt = pyplot()
    fig, ax = plt.subplots()
    ax.plot([0, 1], [1, 0])
    path = save(fig, tmp_path / "a" / "b" / "fig.png", dpi=50)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in path.parent.iterdir()) == ["fig.png"]  # no temporary file left
    assert not plt.fignum_exists(fig.number)


def test_failed_save_leaves_nothing(tmp_path):
    plt = pyplot()
    fig, _ = plt.subplots()
    with pytest.raises(ValueError):
        save(fig, tmp_path / "fig.notaformat")
    assert list(tmp_path.iterdir()) == []
    assert not plt.fignum_exists(fig.number)
