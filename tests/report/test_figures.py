"""The figures draw only what the data support (issue 48 item 4): an unexplained smooth whose level the model's span
carries is drawn as its shape, with the shape's band, never with the level's band nor without one it has."""

import math

import pytest

from torchcal.report import markdown


def _entry(with_shape_se: bool) -> dict:
    grid = [k / 49 * 2.5 for k in range(50)]
    value = [3e-3 + 2e-4 * math.sin(4 * x) for x in grid]  # 3 mrad level, 0.2 mrad shape
    smooth = {"grid": grid, "value": value, "se": [5e-3] * 50, "unit": "rad"}  # the level's uncertainty: 5 mrad
    if with_shape_se:
        smooth["se_shape"] = [5e-5] * 50
    return {"variable": "q5", "label": "q5 [rad]", "share": 0.03, "p_bonferroni": 1e-40, "smooth": smooth}


@pytest.mark.parametrize("with_shape_se", [True, False])
def test_an_undetermined_level_is_drawn_as_its_shape_with_the_shapes_band(monkeypatch, tmp_path, with_shape_se):
    drawn = {}

    def keep(fig, path, *a, **k):
        drawn["ax"] = fig.axes[0]

    monkeypatch.setattr(markdown, "save", keep)
    markdown.plot_unexplained(_entry(with_shape_se), tmp_path / "u.png")
    ax = drawn["ax"]
    (line,) = ax.get_lines()[:1]
    y = line.get_ydata()
    assert abs(sum(y) / len(y)) < 1e-6 and max(abs(v) for v in y) < 250  # about zero [urad], the level gone
    bands = ax.collections
    assert len(bands) == (1 if with_shape_se else 0)
    if with_shape_se:  # +-2 x 50 urad about the shape, not +-2 x 5 mrad
        ys = bands[0].get_paths()[0].vertices[:, 1]
        assert ys.max() < 350 and ys.min() > -350
