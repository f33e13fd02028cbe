"""The checks on the chosen system: each failed check is a sentence (a doubt) saying
what failed and what to try. Held-out score, convergence and significance
(:func:`doubts`), terms exchangeable, weak or missing, constants that differ between
recordings, a first integral not preferred, and the whole-recording run."""

from __future__ import annotations

import numpy as np

from ..._core.doubt import Doubt
from ..fit.refine import CONTINUOUS

# A closed system reproduces held-out data when its score (held-out misfit in noise
# variances) is ~1. The noise level is itself estimated from the data (to ~10%), so a
# score is called too high only when it exceeds 1 + REPRODUCTION_SLACK by two standard
# errors. Over the discovery benchmark's correct results the largest
# score - 2 se was 1.07; a missing term or hidden state gives more.
REPRODUCTION_SLACK = 0.15
# A score this many times the reference is no reproduction however wide its standard
# error: a few held-out segments (sparse samples, short recordings) can leave the error
# so wide that "not significantly above" would pass a law that misses one segment by
# hundreds of noise variances (prey-only Lotka-Volterra, a panel of 20 x 11 samples: a
# wrong law at 673 +- 480).
FAR = 3.0
# Reference (a right system's simulated held-out score) above which the check has
# little power: a law that misses the data by a few noise variances per sample scores
# within the reference's own spread (epidemic panels of 20 x 11 samples: a wrong law at
# 11.3 +- 3.7 against a reference of 7.5).
POWER = 3.0
SIGNIFICANCE = 2.0  # a kept coefficient should be this many standard errors from zero
# Held out by whole recordings, a check whose two standard errors exceed this many noise
# variances could not tell a law that misses every sample by a noise variance from a
# right one (indomethacin's 6 subjects: +-0.87; panels of 10-20 recordings: 0.03-0.26).
SCORE_RESOLUTION = 1.0


def reproduces(score, score_se, expected=1.0) -> bool:
    """Whether a held-out score is within two standard errors of ``expected`` (a right
    system's score: about 1 noise variance, or :mod:`..fit.expected_score`'s
    simulated reference where short segments leave their starts uncertain), with
    ``REPRODUCTION_SLACK`` for the estimated noise level, and at most ``FAR`` times
    that."""
    limit = max(expected, 1.0) * (1 + REPRODUCTION_SLACK)
    return score - SIGNIFICANCE * score_se <= limit and score <= FAR * limit


def doubts(score, score_se, refinement, terms, hidden, unscored=None, expected=None,
           out_of_time=False):
    """The checks a refined system fails, each as a sentence with its remedy (its
    segments apart: :attr:`..fit.refine.Fit.continuous`); ``unscored`` is why it has
    no score ("not judged": ``max_time`` ran out first); ``expected``: a right system's
    simulated score here (None: about 1; with ``out_of_time``, ``max_time`` left that
    reference out, and the score doubt says so)."""
    found = []
    if unscored == "not judged":
        found.append(Doubt("not scored", "the closed system was not scored on held-out "
                           "data (max_time was spent first): it was not checked against "
                           "the data"))
    elif not (np.isfinite(score) and np.isfinite(score_se)):
        found.append(Doubt("not scored",
                     "the closed system could not be scored on held-out data (its "
                     "integration blew up, or its hidden states jump between integration "
                     "segments): it was not checked against the data"))
    elif not reproduces(score, score_se, expected or 1.0):
        reference = (f"~{max(expected, 1.0):.3g} for a right system at this sampling, "
                     "simulated" if expected is not None else
                     "~1; a right system's score at this sampling was not simulated (max_time "
                     "was spent first) and may be higher" if out_of_time else "~1")
        found.append(Doubt(
            "score",
            f"the closed system does not reproduce held-out data down to their noise (score "
            f"{score:.3g} +- {score_se:.2g}, expected {reference}): a term or a hidden "
            "state is probably missing; try a richer library or closure_library, or more "
            "data"))
    if not refinement.continuity_gap <= CONTINUOUS:
        found.append(Doubt(
            "not continuous",
            f"the closed system's integration segments end up to "
            f"{refinement.continuity_gap:.3g} noise levels from where the next one starts: "
            "the fit is no trajectory of the system, so its terms (missing, weak, "
            "exchangeable, beyond the library) and its score's reference were not checked; "
            "a term or a hidden state is probably missing: try a richer library or "
            "closure_library, or more hidden states"))
    if refinement.status != "converged":
        found.append(Doubt(
            "not converged",
            f"refinement by integration stopped at its iteration limit ({refinement.status}, "
            f"{refinement.iterations} iterations): the coefficients are not a converged fit"))
    weak = [f"d{t.state}/dt: {t.feature}" for t in terms
            if t.state in hidden and not t.fixed and np.isfinite(t.stderr)
            and abs(t.value) < SIGNIFICANCE * t.stderr]
    if weak:
        found.append(Doubt(
            "insignificant",
            f"{len(weak)} hidden-equation coefficient(s) within {SIGNIFICANCE:g} standard "
            f"errors of zero ({', '.join(weak[:4])}{', ...' if len(weak) > 4 else ''}): "
            "the data do not determine them"))
    return tuple(found)


def weak_check_doubts(expected, unaided=None, scored=True, recordings=None,
                      out_of_time=False):
    """The ``weak check`` doubt when the held-out check has little power on these data
    (a right system's simulated score ``expected`` above ``POWER``), or, for a law found
    without stage one (``unaided`` says why: then the check is the only one that could
    see a wrong carrier's approximation), when its power could not be measured (a
    scored system that could not be simulated and refitted, or, with ``out_of_time``,
    whose reference ``max_time`` left out). ``recordings``: (count, standard error of
    the score) where whole recordings were held out; the check is weak when two
    standard errors exceed ``SCORE_RESOLUTION``."""
    if (recordings is not None and scored and np.isfinite(recordings[1])
            and SIGNIFICANCE * recordings[1] > SCORE_RESOLUTION):
        count, se = recordings
        return (Doubt("weak check", f"the held-out check left out whole recordings, and "
                      f"{count} leave its score uncertain by +-{se:.2g} noise variances: a "
                      "law that misses the data by a noise variance could pass it. Confirm "
                      "it with more recordings."),)
    if expected is None and not (unaided and scored):
        return ()
    if expected is not None and expected <= POWER:
        return ()
    power = ("its power was not measured (max_time was spent first)" if expected is None
             and out_of_time else
             "its power could not be measured (the fitted system could not be simulated "
             "and refitted)" if expected is None else
             f"little power (a right system would score ~{expected:.3g} noise variances "
             "here: what it holds out is predicted from a few noisy samples)")
    why = f"{unaided}; on" if unaided else "On"
    return (Doubt("weak check", f"{why} these data the held-out check has {power}, so a "
                  "law that misses the data by a few noise variances could pass it. Confirm "
                  "it with denser samples or more recordings."),)


def segment_constant_doubts(terms, names, n_observed, trajectories, stds):
    """A hidden state without dynamics (``dh/dt = 0``) is one constant per recording (or
    gap-separated segment): when those constants differ beyond their standard errors,
    the recordings do not share one law (each gets its own parameter). A doubt per such
    state; also one when a constant cannot be read (a trajectory blew up)."""
    if len(trajectories) < 2:
        return ()
    moving = {t.state for t in terms if t.value != 0}
    found = []
    for a, name in enumerate(names):
        if name in moving:
            continue
        col = n_observed + a
        values = np.array([tr[0, col] for tr in trajectories])
        if not np.all(np.isfinite(values)):
            found.append(Doubt(
                "recording constant",
                f"{name} has no dynamics of its own and its constant could not be read in "
                "every recording (an integration blew up): whether the recordings share "
                "one law was not checked"))
            continue
        errors = np.array([sd[0, col] for sd in stds])
        spread = np.abs(values[:, None] - values[None, :])
        bound = SIGNIFICANCE * np.sqrt(errors[:, None] ** 2 + errors[None, :] ** 2)
        if np.any(spread > np.where(np.isfinite(bound), bound, 0.0)
                  + 1e-9 * np.max(np.abs(values))):
            found.append(Doubt(
                "recording constant",
                f"{name} has no dynamics of its own but takes different constant values in "
                f"different recordings or segments ({', '.join(f'{v:.4g}' for v in values[:5])}"
                f"{', ...' if len(values) > 5 else ''}): they do not share one law (each "
                "has its own parameter); the system may describe each recording's trend "
                "rather than the dynamics. Longer recordings, or a hidden state with an "
                "equation of its own, are needed"))
    return tuple(found)


