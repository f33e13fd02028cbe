"""One-line reprs of estimators: the class and the parameters that differ from their
defaults, as scikit-learn prints them."""

import numpy as np

from latentsindy._core.reprs import estimator_repr


class Model:
    def __init__(self, library=None, *, support=None, seed=0, name="a"):
        self.library, self.support, self.seed, self.name = library, support, seed, name

    def params(self):
        return {"library": self.library, "support": self.support, "seed": self.seed,
                "name": self.name}


def test_defaults_are_left_out():
    assert estimator_repr(Model(), Model().params()) == "Model()"
    m = Model(seed=3, name="b")
    assert estimator_repr(m, m.params()) == "Model(seed=3, name='b')"


def test_arrays_are_shown_by_their_shape():
    m = Model(support=np.ones((2, 5), dtype=bool))
    assert estimator_repr(m, m.params()) == "Model(support=<array of shape (2, 5)>)"


def test_long_reprs_break_one_parameter_a_line():
    m = Model(library="x" * 60, name="y" * 40)
    text = estimator_repr(m, m.params())
    assert text.splitlines() == ["Model(library='" + "x" * 60 + "',",
                                 "      name='" + "y" * 40 + "')"]
