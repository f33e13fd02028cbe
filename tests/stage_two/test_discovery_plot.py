"""The discovery figure: what it draws, the file it writes, and the message without
matplotlib."""

import sys

import matplotlib
import numpy as np
import pytest

matplotlib.use("Agg")


def test_discovery_plot_draws_data_model_hidden_and_truth(lv, tmp_path):
    """One panel per observed and hidden state; the hidden panel has the fitted series,
    its band and the truth mapped into its units (which matches it: noise-free LV)."""
    data, result = lv
    path = tmp_path / "lv.png"
    fig = result.plot(truth=data.x_clean[:, 1], path=path)
    assert path.stat().st_size > 10_000
    observed_ax, hidden_ax = fig.axes
    assert "confident" in fig._suptitle.get_text()
    assert "NOT" not in fig._suptitle.get_text()
    labels = [line.get_label() for line in hidden_ax.get_lines()]
    assert labels == ["h (fitted)", "truth (affine map)"]
    fitted, truth = (line.get_ydata() for line in hidden_ax.get_lines())
    np.testing.assert_allclose(truth, fitted, atol=1e-3 * np.ptp(fitted))
    assert len(hidden_ax.collections) == 1  # the band
    sim_line = observed_ax.get_lines()[1]
    np.testing.assert_allclose(sim_line.get_ydata(), data.x[:, 0], atol=1e-2 * np.ptp(data.x))


def test_discovery_plot_refuses_truth_of_the_wrong_length(lv):
    data, result = lv
    with pytest.raises(ValueError, match=r"truth must have shape .* n_times = 2000; got "
                                         r"shape \(10,\)"):
        result.plot(truth=np.zeros(10))


def test_plots_without_matplotlib_name_the_extra(lv, monkeypatch):
    _, result = lv
    monkeypatch.setitem(sys.modules, "matplotlib.pyplot", None)
    with pytest.raises(ImportError, match=r'pip install "latentsindy\[plot\]"'):
        result.plot()
    with pytest.raises(ImportError, match=r'pip install "latentsindy\[plot\]"'):
        result.coefficients.plot()
