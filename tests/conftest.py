import numpy as np
import pytest
import torch

torch.set_num_threads(2)


def r2(estimate, truth):
    """Coefficient of determination of ``estimate`` against ``truth``."""
    estimate, truth = np.asarray(estimate), np.asarray(truth)
    return 1.0 - np.sum((estimate - truth) ** 2) / np.sum((truth - truth.mean()) ** 2)


def transition_time(t, series, low, high):
    """First time the series crosses the midpoint between ``low`` and ``high``."""
    mid = 0.5 * (low + high)
    above = (series - mid) * np.sign(high - low) > 0
    return float(t[np.argmax(above)])


@pytest.fixture
def fast():
    """Training options for tests that check plumbing rather than accuracy."""
    return {"support_steps": 40, "refit_steps": 40}
