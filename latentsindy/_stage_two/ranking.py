"""Ranking scored verdicts: the sparsest system the held-out data do not reject wins,
and the others that the data cannot tell from it make the result uncertain.

:func:`rank` applies the one-standard-error rule to the held-out scores, with paired
errors on the same held-out units (:func:`paired_evidence`) where the scores' own
standard errors hide a consistent difference.
"""

from __future__ import annotations

import numpy as np
from scipy import stats

from .context import TIE
from .fit.field import ParametricSystem
from .verdict import Verdict

__all__ = ["paired_evidence", "rank", "same_structure"]

# One-sided level of :func:`paired_evidence`: the held-out data favour one system over
# another when its paired errors are lower with this confidence (t test over held-out
# units: segments, recordings or samples).
FAVOURED = 0.975
# One-sided level at which the held-out data lean towards a system (its paired errors
# lower by about one standard error of their differences): stage one's own law, larger
# than the chosen one and not it with terms added, scoring no worse and leaned
# towards, makes the result uncertain (:func:`_rival`).
LEANS = 0.84


def rank(verdicts):
    """Verdicts ordered by choice: among the scored ones, the sparsest that the held-out
    data do not reject against the best score (within one standard error of it, or not
    worse on the same segments by :func:`paired_evidence`) first; returns (ordered,
    uncertain) where ``uncertain`` lists the others in that band whose hidden states
    are not a superset of the chosen one's (other carriers) and that are no larger than
    it or favoured over it by the held-out data, and stage one's own law where it
    scores no worse and the held-out data lean towards it (:func:`_rival`): structures
    the data cannot tell apart. Systems in the band that only add terms or hidden
    states to the chosen one, or are larger and fit no better, are parsimony's call.
    With no scored verdict, the smallest comes first (those that do not join last)."""
    unique = []
    for v in sorted(verdicts, key=lambda v: (not v.scored, v.cv)):
        if not any(same_structure(v, u) for u in unique):
            unique.append(v)  # the same final system reached twice counts once
    verdicts = unique
    finite = [v for v in verdicts if v.scored and np.isfinite(v.cv)]
    if not finite:  # a fit that is no trajectory of its system comes last; contenders
        # left unscored by max_time first, the best in-sample misfit first among them
        return sorted(verdicts, key=lambda v: (
            v.history[:1] == ("does not join",), v.history[:1] != ("not judged",),
            v.cv if v.history[:1] == ("not judged",) else v.size)), []
    best = min(finite, key=lambda v: v.cv)
    band = max(best.cv + best.cv_se, TIE)
    inside = [v for v in finite
              if v.cv <= band or not paired_evidence(best, v, unpaired=True)]
    # equal sizes: fewer terms in the observed equations first. A hidden state can be
    # shifted by any function of the observed states that the library holds (prey-only
    # LV: h + d x with xdot = x h + d x^2 is the same system, same size); the variable
    # that needs the fewest observed terms is the one that carries the dynamics.
    chosen = min(inside, key=lambda v: (v.size, _observed_terms(v), v.cv))
    ids = {id(v) for v in inside}
    rest = sorted([v for v in verdicts if v is not chosen],
                  key=lambda v: (not v.scored, id(v) not in ids,
                                 v.size if id(v) in ids else 0, v.cv))
    uncertain = [v for v in rest if id(v) in ids and (
        not _extends(v, chosen)
        and (v.size <= chosen.size or paired_evidence(v, chosen, unpaired=True))
        or _rival(v, chosen))]
    return [chosen] + rest, uncertain


def _rival(v, chosen) -> bool:
    """Whether ``v`` is stage one's own law (:attr:`.proposal.Proposal.stage_one`),
    larger than ``chosen`` and not ``chosen`` with terms added, scoring no worse, the
    chosen within one standard error of it and above ``TIE``, and the held-out data
    leaning towards it (``LEANS``, paired errors only).

    Stage one's law is the method's estimate: its terms chosen by stage one's evidence,
    its hidden states the coefficients that vary. The judge replaces it by a sparser law
    that scores as well (parsimony), which between nested systems is the data's call:
    added terms that buy no held-out accuracy are not in them. Between laws that are not
    nested it is only a tie-break; where stage one's law predicts held-out data at least
    as well, the sparser one is not shown to be the law. Two species competing to
    coexistence, x seen through one rise and settling at 5% noise: ``dx/dt = h x^2``,
    ``dh/dt = -1.02 h - 0.46 x^2`` (3 parameters; the true law, in the coefficient of x,
    has 7) was reported confident, while stage one's ``dx/dt = h x^2 + 0.97 x``,
    ``dh/dt = -0.07 h - 0.25`` (4) scored 0.004 lower (paired differences 1.3 standard
    errors below zero). Other larger laws are not counted here: prey-only Lotka-Volterra
    has close approximations in other carriers (``h x^2`` with a fuller closure, 6-9
    parameters) that lean against the exact law in about one draw in ten by chance
    (nine of 137 exact results in ``conditions.py`` when they were counted). Scores
    within ``TIE`` of zero are ties (noise-free data: a modulated oscillator's exact law
    at 9.2e-6 noise variances against stage one's at 8.4e-6, leaning by rounding)."""
    return (v.proposal.stage_one and not v.proposal.nested and v.size > chosen.size
            and v.cv <= chosen.cv <= v.cv + v.cv_se and chosen.cv > TIE
            and not _nests(v, chosen) and paired_evidence(v, chosen, level=LEANS))


def paired_evidence(better, worse, unpaired=False, level=FAVOURED) -> bool:
    """Whether the held-out data favour ``better`` over ``worse``: its error is lower on
    the same held-out units (segments; recordings or samples where those are held out,
    :mod:`.fit.held_out`) by more than the t quantile (``level``, one-sided, degrees
    of freedom: units - 1) times the standard error of the paired differences. Units
    held out in one fold share its refit, so the evidence is somewhat overstated.

    Pairing removes what the segments share (a hard stretch of data is hard for every
    system), so it resolves differences that the scores' own standard errors hide; the
    t quantile keeps a few segments (sparse samples: 4-8) from reading as strong
    evidence. A larger alternative in the band makes the result uncertain only when
    favoured: its extra parameters are priced by holding out (each fold refits without
    the segment, so parameters that fit noise raise its held-out error), and scoring
    merely as well is no evidence for them (prey-only LV at random times: ``dx/dt = h
    x^2`` with a five-term closure, within one standard error of the exact law, paired
    difference nil). Without paired errors (scored on other segments) the answer is
    ``unpaired``: the band alone decides."""
    a, b = getattr(better, "errors", None), getattr(worse, "errors", None)
    if a is None or b is None or np.shape(a) != np.shape(b) or len(a) < 3:
        return unpaired
    d = np.asarray(b) - np.asarray(a)
    se = d.std(ddof=1) / np.sqrt(len(d))
    return bool(d.mean() > stats.t.ppf(level, len(d) - 1) * se)


def _observed_terms(v):
    system = v.system
    rows = slice(0, getattr(system, "n_observed", 0))
    return int(((system.coef[rows] != 0) | system.free[rows]).sum())


def _extends(v, chosen):
    """Whether ``v``'s hidden states include all of ``chosen``'s (same defining terms,
    at least the same order): then ``v`` is the chosen system with more in it, and
    parsimony, not uncertainty, decides between them."""
    a, b = v.proposal, chosen.proposal
    return (set(b.structure.pivots) <= set(a.structure.pivots) and a.order >= b.order
            and len(a.nested) >= len(b.nested))


def _nests(v, chosen) -> bool:
    """Whether ``v`` is ``chosen`` with terms (or hidden states) added: it extends it
    (:func:`_extends`) and keeps every one of its terms."""
    return _extends(v, chosen) and _term_set(chosen.system) <= _term_set(v.system)


def _term_set(system):
    used = (np.asarray(system.coef) != 0) | np.asarray(system.free)
    rows, cols = np.nonzero(used)
    return {(system.state_names[i], str(system.features[j]))
            for i, j in zip(rows, cols, strict=True)}


def same_structure(a: Verdict, b: Verdict) -> bool:
    return _same_terms(a.system, b.system)


def _same_terms(a: ParametricSystem, b: ParametricSystem) -> bool:
    return (a.state_names == b.state_names and a.features == b.features
            and np.array_equal(a.free | (a.coef != 0), b.free | (b.coef != 0)))
