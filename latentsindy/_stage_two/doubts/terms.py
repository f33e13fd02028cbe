"""Doubts about the chosen system's terms: terms the data could exchange for others,
terms they support only weakly, and terms left out that they nearly call for. Each is
found by refitting the integrated system (:mod:`..fit.terms`) and said as a doubt."""

from __future__ import annotations

import numpy as np

from ..._core.doubt import Doubt
from ..context import MARGIN
from ..fit.shooting import BlowUp
from ..fit.terms import ambiguities, missing_terms, weak_terms
from ..rewrite.gauge import same_up_to_shift
from ..verdict import Verdict


def exchangeable_terms(verdict: Verdict):
    """Terms of the chosen system that others could replace as well
    (:func:`.terms.ambiguities`): [(move, misfit change)]. An exchange whose refit is
    the chosen system with a hidden state shifted by a function of the observed states
    (:func:`.gauge.same_up_to_shift`) is the same law in another variable, not one."""
    if not verdict.scored or verdict.candidates is None:
        return []
    try:
        return ambiguities(verdict.problem, verdict.fit, verdict.candidates,
                           same=lambda trial: same_up_to_shift(verdict.fit, trial))
    except BlowUp:
        return []


def weakly_supported_terms(verdict: Verdict):
    """Terms of the chosen system that the data support only weakly
    (:func:`.terms.weak_terms`): [(cell, misfit change, bar)]."""
    if not verdict.scored or verdict.candidates is None:
        return []
    try:
        return weak_terms(verdict.problem, verdict.fit, verdict.candidates)
    except BlowUp:  # not checked is a doubt, not a pass
        return [(None, np.nan, np.nan)]


def nearly_needed_terms(verdict: Verdict):
    """Terms left out of the chosen system that the data nearly call for
    (:func:`.terms.missing_terms`): [(cell, misfit change, price)]."""
    if not verdict.scored or verdict.candidates is None:
        return []
    try:
        return missing_terms(verdict.problem, verdict.fit, verdict.candidates)
    except BlowUp:
        return []


def _term_text(cell, system, rename, names_map):
    r, c = cell
    state = system.state_names[r]
    return f"{system.features[c].xreplace(rename)} in d{names_map.get(state, state)}/dt"


def weak_doubts(found, system, rename, names_map):
    """A sentence per term the data support only weakly, or whose support could not be
    checked."""
    out = []
    for cell, change, bar in found:
        if cell is None:
            out.append(Doubt("weak term",
                       "the support of the terms could not be checked (refitting without "
                       "a term blew up): they may include terms the data do not need"))
        elif not np.isfinite(change):
            out.append(Doubt("weak term",
                       f"the support of {_term_text(cell, system, rename, names_map)} could "
                       "not be checked (refitting without it failed): it may stand for a "
                       "small systematic error rather than part of the law"))
        else:
            out.append(Doubt(
                "weak term",
                f"the data support {_term_text(cell, system, rename, names_map)} only weakly "
                f"(dropping it raises the misfit by {change:.3g} residual variances, under "
                f"the {bar:.3g} that very strong evidence needs): it may stand for a small "
                "systematic error rather than part of the law"))
    return tuple(out)


MISSING_SHOWN = 3  # left-out terms named one by one; the rest are counted


def missing_doubts(found, system, rename, names_map):
    """A sentence per term left out that the data call for, or nearly do (the nearest
    ``MISSING_SHOWN``; one sentence counts the rest)."""
    out = []
    for cell, change, price in found[:MISSING_SHOWN]:
        term = _term_text(cell, system, rename, names_map)
        if change + price < 0:  # selection could not take it (its fit failed to join)
            out.append(Doubt("missing term",
                       f"{term} was left out, but the data call for it (adding it lowers "
                       f"the misfit by {-change:.3g} residual variances, more than the "
                       f"{price:.3g} a term costs): the law probably includes it"))
        else:
            out.append(Doubt("missing term",
                       f"{term} was left out, but the data nearly call for it (adding it "
                       f"lowers the misfit by {-change:.3g} residual variances, within "
                       f"{MARGIN:g} of the {price:.3g} a term costs): the law may include it"))
    if len(found) > MISSING_SHOWN:
        out.append(Doubt("missing term",
                   f"{len(found) - MISSING_SHOWN} more left-out terms would each lower the "
                   "misfit by nearly a term's cost or more: the law may be larger"))
    return tuple(out)


def exchange_doubts(moves, system, rename, names_map):
    """A sentence per term exchange the data do not refuse."""
    def term(cell):
        return _term_text(cell, system, rename, names_map)

    out = []
    for (kind, (gone, new)), change in moves:
        gone = " and ".join(term(g) for g in gone) if kind != "swap" else term(gone)
        new = " and ".join(term(g) for g in new) if kind == "exchange" else term(new)
        what = ("a smaller system fits almost as well" if kind == "merge"
                else "an equally good system")
        out.append(Doubt("exchangeable term",
                   f"the data cannot tell {gone} from {new} (exchanging them changes the "
                   f"misfit by {change:+.2g} residual variances): {what}"))
    return tuple(out)


def beyond_doubts(found, system, rename, names_map):
    """A sentence for the terms outside every candidate system that the data call for
    (:mod:`.beyond`): the nearest ``MISSING_SHOWN`` named, the rest counted."""
    if not found:
        return ()
    shown = "; ".join(f"{_term_text(cell, system, rename, names_map)} (misfit "
                      f"{change:+.3g} residual variances, a term costs {price:.3g})"
                      for cell, change, price in found[:MISSING_SHOWN])
    more = (f", and {len(found) - MISSING_SHOWN} more" if len(found) > MISSING_SHOWN
            else "")
    return (Doubt("beyond library",
            f"the data strongly call for terms no candidate system held: {shown}{more}. The law "
            "found is probably an approximation of one that needs higher powers in the "
            "hidden laws or a hidden state in more observed terms; try hidden_terms, more "
            "data, or a closure_library of higher degree (which can find another "
            "approximation: compare its result with this one)"),)
