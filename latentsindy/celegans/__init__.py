"""The C. elegans workflow of the seed paper (main text 4.5, supplement 3).

Load the Kato et al. (2015) recordings in either public layout, take the first principal
component x of each worm, and fit ``xdot = y``, ``ydot = a x^3 + b x^2 + c x + d y + u(t)``
with u a two-level switch, constants shared across worms and the switch per worm.

>>> from latentsindy import celegans
>>> rec, truth = celegans.switching_worm(n_frames=1500, seed=1)
>>> model = celegans.fit_switching_model(rec, stage_one=False)
>>> abs(model.cubic["x^3"] / truth.cubic["x^3"] - 1) < 0.1
True

With files: ``celegans.load_kato("WT_NoStim.mat")`` or
``celegans.load_kato("wbdata/")`` (per-worm files plus ``sevenStateColoring.mat``).
"""

from ._dynamics import FixedPoint, fixed_points
from ._loaders import load_kato, load_kato_worm, load_wt_nostim
from ._plots import plot_model
from ._recording import Component, WormRecording
from ._switch import Switch, sigmoid_switch, two_level_switch
from ._synthetic import (
    KATO_FPS,
    PAPER_CUBIC,
    PAPER_LEVELS,
    SwitchingTruth,
    switching_worm,
    write_kato_folder,
    write_wt_nostim,
)
from ._workflow import SwitchingModel, WormFit, fit_switching_model

__all__ = [
    "load_kato",
    "load_kato_worm",
    "load_wt_nostim",
    "WormRecording",
    "Component",
    "fit_switching_model",
    "SwitchingModel",
    "WormFit",
    "Switch",
    "two_level_switch",
    "sigmoid_switch",
    "FixedPoint",
    "fixed_points",
    "plot_model",
    "switching_worm",
    "SwitchingTruth",
    "write_kato_folder",
    "write_wt_nostim",
    "PAPER_CUBIC",
    "PAPER_LEVELS",
    "KATO_FPS",
]
