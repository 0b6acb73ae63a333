"""Plots read like an instrument: titles clear of colour bars, legends clear of the data,
one quantity and unit per axis, rounding noise drawn as constant."""

import numpy as np
import pytest

import lfsim
from lfsim.analysis import ini_plots


@pytest.fixture(scope="module")
def figures(tmp_path_factory):
    """The figures ``lfsim analyze`` draws for the ideal InI design (kept open for inspection)."""
    import matplotlib

    matplotlib.use("Agg")
    from lfsim.analysis.ini_analysis import analyze

    kept = {}
    real = ini_plots.save_figure

    def keep(fig, path, **kw):
        fig.canvas.draw()
        kept[path.name] = (fig, fig.canvas.get_renderer())
        real(fig, path, **kw)

    mp = pytest.MonkeyPatch()
    mp.setattr(ini_plots, "save_figure", keep)
    mp.setattr(ini_plots._plt(), "close", lambda fig=None: None)
    try:
        analyze(lfsim.load("scenes/ini_freeform_optimized.toml"), tmp_path_factory.mktemp("an"), stride=(8, 4))
    finally:
        mp.undo()
    return kept


def _overlap(a, b) -> bool:
    return a.x0 < b.x1 and b.x0 < a.x1 and a.y0 < b.y1 and b.y0 < a.y1


def test_contrast_map_title_clear_of_the_colour_bar(figures):
    fig, rend = figures["contrast_map.png"]
    bar = fig.axes[1].get_window_extent(rend)
    titles = [t for t in [fig._suptitle, fig.axes[0].title] if t is not None and t.get_text()]
    assert titles
    for t in titles:
        assert not _overlap(t.get_window_extent(rend), bar), t.get_text()


def test_footprint_legend_covers_no_footprint(figures):
    fig, rend = figures["footprints.png"]
    ax = fig.axes[0]
    legend = ax.get_legend().get_window_extent(rend)
    assert not _overlap(legend, ax.get_window_extent(rend))
    assert "paraxial" in [t.get_text() for t in ax.get_legend().get_texts()]


def test_before_after_one_unit_per_axis(tmp_path):
    import matplotlib.pyplot as plt

    from lfsim.optimize import workflow

    figs = []
    s = {"gd_max_deg": 1.2, "gd_mean_deg": 0.5, "pa_max": 0.4, "pa_mean": 0.2, "contrast_nyquist_min": 0.1,
         "contrast_nyquist_mean": 0.3, "rms_spot_mean_arcmin": 2.0, "gd_target_deg": 0.75, "pa_target": 0.3}
    orig_close = plt.close
    plt.close = lambda fig=None: figs.append(fig)
    try:
        table = workflow.compare({"summary": s}, {"summary": {**s, "gd_max_deg": 0.6}}, tmp_path / "ba.png")
    finally:
        plt.close = orig_close
    assert table["gd_max_deg"] == {"before": 1.2, "after": 0.6}
    labels = [ax.get_ylabel() for ax in figs[0].axes]
    assert labels == ["GD (Eq. 11), deg", "PA (Eq. 12)", "contrast at Nyquist", "RMS spot, arcmin"]
    targets = [[ln.get_ydata()[0] for ln in ax.get_lines()] for ax in figs[0].axes]
    assert targets[:2] == [[0.75], [0.3]]


def test_sweep_rounding_noise_drawn_as_constant():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lfsim.tolerance.sweep import _flatten, unit_of

    fig, (a, b) = plt.subplots(1, 2)
    noise = [1.45e-15, 0.5e-15, 1.3e-15]
    a.plot([0, 1, 2], noise)
    assert _flatten(a, noise)
    lo, hi = a.get_ylim()
    assert hi - lo >= 2e-3 and lo < np.mean(noise) < hi  # no 1e-15 "trend"
    trend = [0.8063, 0.8062, 0.8061]
    b.plot([0, 1, 2], trend)
    assert not _flatten(b, trend)
    plt.close(fig)
    d = lfsim.load("scenes/ini_ideal.toml")
    assert unit_of(d, "MLA.tilt_z") == "deg" and unit_of(d, "mla.pitch_x") == "mm"
    assert unit_of(d, "ini.tunable.power_diopters[0]") == "D" and unit_of(d, "ini.analysis.fields") == ""
