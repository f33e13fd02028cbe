"""Stage two's independent pieces on a second core give the same discovery, digit for
digit, as one process alone."""

import os
import sys

import numpy as np
import pysindy as ps
import pytest

from latentsindy import discover_hidden, systems
from latentsindy._core import parallel

pytestmark = pytest.mark.skipif(sys.platform != "linux" or len(os.sched_getaffinity(0)) < 2,
                                reason="the helper needs Linux and two cores")


def prey_only():
    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=1000, noise=0.01, seed=4)
    return discover_hidden(data.x[:, :1], ps.PolynomialLibrary(degree=3), t=data.t,
                           feature_names=["x"], verbose=False)


def test_a_discovery_is_the_same_with_the_second_process_and_without(monkeypatch):
    returned = []
    collect = parallel._collect

    def counted(*args):
        results = collect(*args)
        returned.append(len(results))
        return results

    monkeypatch.setattr(parallel, "_collect", counted)
    both = prey_only()
    # pieces were shared, and the helper's results came back (pickled and used)
    assert returned and sum(returned) > 0, returned
    previous = parallel.enable(False)
    try:
        alone = prey_only()
    finally:
        parallel.enable(previous)
    assert both.summary() == alone.summary()
    assert both.rhs == alone.rhs
    assert both.score == alone.score and both.score_se == alone.score_se
    assert np.array_equal(both.hidden, alone.hidden)
    assert [a.score for a in both.alternatives] == [a.score for a in alone.alternatives]
    assert both.doubts == alone.doubts
