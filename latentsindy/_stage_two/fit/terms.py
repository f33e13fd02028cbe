"""Term selection on the integrated likelihood: drops, additions, swaps, merges and
exchanges.

A closed system's terms are chosen by the extended Bayesian information criterion of
its fit by integration: ``misfit / s^2 + k (log(n) + log(p))`` (misfit in noise
variances, ``s^2`` the residual variance, never below 1 so exact data do not make the
integrator's own error look like signal; ``k`` free coefficients, ``n`` data, ``p`` the
pool of terms searched). Greedy backward elimination
alone goes wrong among collinear terms (at 10% noise on prey-only Lotka-Volterra it
drops the real ``x`` and keeps ``x^2`` and ``h^2`` that compensate), so every step
considers dropping a term, adding a candidate, swapping one for another, merging
two into one, and (when none of these helps) exchanging two terms of an equation for
two others (a combination of terms that is nearly constant along the data, such as
an oscillator's energy ``a x^2 + b y^2``, stands in for the constant term; only a move
that removes both and adds the constant finds the smaller system).

All moves are scored at once on the fit's local quadratic model (Gauss-Newton: the
normal equations at the current point, the segment starts eliminated by their Schur
complement, so each move costs a solve the size of the coefficient count); the best
one is then refitted exactly and kept only if the exact criterion improves.
"""

from __future__ import annotations

import numpy as np
import torch

from ..._core.budget import spent
from ..._core.parallel import available, forked_map
from ..._core.timing import timed
from ..context import MARGIN
from .field import ParametricSystem
from .least_squares import HOPELESS, degrees_of_freedom
from .quadratic import Quadratic
from .refine import Fit, Problem
from .shooting import BlowUp

MAX_STEPS = 12
MAX_ATTEMPTS = 3  # exact refits tried per step before giving up
# Exchanging terms that changes the misfit by less than this (residual variances) is not
# refused by the data: a likelihood-ratio difference of 4 is two standard errors of one
# coefficient.
AMBIGUITY = 4.0
# A kept term is doubted when dropping it raises the misfit by less than the price of a
# term plus this (residual variances): twice the log Bayes factor for the term is then
# under 10, short of "very strong" evidence (Kass & Raftery 1995). Such a term passed the
# criterion, but a small systematic error (smoothing bias, a slightly wrong hidden law)
# buys that much fit as easily as a law does.
EVIDENCE = 10.0


@timed("term selection")
def select_terms(problem: Problem, fit: Fit, candidates, max_steps=MAX_STEPS):
    """Improve the set of free coefficients of ``fit.system`` by BIC; ``candidates``
    (bool, like ``system.free``) are the coefficients that may be added. Returns the
    final fit and the moves made: ("drop"/"add", cell, predicted BIC change),
    ("swap", (out, in), change), ("merge", ((out, out), in), change),
    ("exchange", ((out, out), (in, in)), change) or ("add pair", (in, in), change)."""
    # extended BIC (Chen & Chen 2008, gamma = 1/2): the price of a term grows with the
    # number of terms it was chosen from, so that searching many candidates does not
    # let one of them in by chance
    price = _price(problem, fit, candidates)
    history, tabu = [], set()
    for _ in range(max_steps):
        if spent("term selection"):  # max_time: the terms selected so far
            break
        s2 = max(fit.residual_variance, 1.0)
        model = Quadratic(problem, fit, candidates & ~fit.system.free)
        base = _bic(fit, s2, price)
        trial = _first_better(problem, fit, model, model.moves(price, s2), base, s2, price,
                              tabu)
        if trial is None:  # no single move helps: exchange two terms of an equation
            trial = _first_better(problem, fit, model, model.exchanges(s2), base, s2, price,
                                  tabu)
        if trial is None:  # nor an exchange: add two terms of an equation together
            trial = _first_better(problem, fit, model, model.pairs(price, s2), base, s2,
                                  price, tabu)
        if trial is None:
            break
        fit, move, gain = trial
        history.append((*move, gain))
    return fit, history


def _first_better(problem, fit, model, moves, base, s2, price, tabu):
    """The first of ``moves`` (best predicted first) whose exact refit lowers the
    criterion, as (fit, move, predicted gain); None after MAX_ATTEMPTS refits."""
    tried = []
    for gain, move, keep in moves:
        if gain <= 1e-6 or len(tried) >= MAX_ATTEMPTS:
            break
        if move not in tabu:
            tried.append((gain, move, keep))

    def line(system):  # the misfit below which the move lowers the criterion
        return s2 * (base - price * system.n_free)

    for (gain, move, _), trial in zip(tried, _refits(problem, fit, model, tried, line),
                                      strict=True):
        # a move whose fit leaves a hidden state jumping between segments (shrunk until
        # its jumps pass the continuity scale) is no system's trajectory: refused
        if trial is not None and _bic(trial, s2, price) < base and problem.joins(trial):
            return trial, move, float(gain)
        tabu.add(move)  # the quadratic model promised more than the exact refit
    return None


def _refits(problem, fit, model, tried, line):
    """The exact refits of the moves ``tried`` (each giving up against ``line``, see
    :func:`_exact_refit`), in order, each made when it is asked for. The first is made
    alone (it usually succeeds, and nothing more is asked); once the second is asked
    for, the first failed, and from the first one asked for while a second core is free
    (:func:`.._core.parallel.available`; inside another map one may come free on the
    way) the rest are made side by side: the same refits, so the same choice."""
    if not tried:
        return
    yield _refit(problem, fit, model, tried[0][2], line)
    rest = tried[1:]
    cpu = torch.device(problem.options.device).type == "cpu"
    for k, move in enumerate(rest):
        # asked before each refit: inside another map, a core may have come free since
        if cpu and available(len(rest) - k):
            yield from forked_map(lambda m: _refit(problem, fit, model, m[2], line), rest[k:])
            return
        yield _refit(problem, fit, model, move[2], line)


def ambiguities(problem: Problem, fit: Fit, candidates, limit=MAX_ATTEMPTS, same=None):
    """Swaps, merges and two-for-two exchanges of ``fit``'s terms that the data do
    not refuse: the exchanged
    system, refitted exactly, is worse by less than ``AMBIGUITY`` residual variances.
    ``same(trial)``, if given, says a refit is ``fit``'s own system in other variables
    (:func:`.gauge.same_up_to_shift`): no ambiguity. Returns [(move, change)], at most
    ``limit`` tried, most plausible first."""
    s2 = max(fit.residual_variance, 1.0)
    model = Quadratic(problem, fit, candidates & ~fit.system.free)
    found = []
    tried = 0
    moves = [m for m in model.moves(0.0, s2) if m[1][0] in ("swap", "merge")]
    for gain, move, keep in sorted(moves + model.exchanges(s2), key=lambda m: -m[0]):
        if -gain >= AMBIGUITY or tried >= limit:
            break
        tried += 1
        trial = _refit(problem, fit, model, keep, lambda _: fit.data_cost + s2 * AMBIGUITY)
        change = None if trial is None else (trial.data_cost - fit.data_cost) / s2
        if change is not None and change < AMBIGUITY and not (same and same(trial)):
            found.append((move, float(change)))
    return found


def weak_terms(problem: Problem, fit: Fit, candidates, limit=MAX_ATTEMPTS):
    """Free coefficients of ``fit`` whose removal (the others refitted exactly) raises
    the misfit by less than the price of a term plus ``EVIDENCE`` residual variances.

    Fails safe: the ``limit`` drops predicted cheapest are refitted exactly; a further
    drop predicted under the bar counts as weak with its predicted change, one whose
    refit fails as weak with change NaN (not checked; a refit that blows up says the
    system needs the term). Returns
    [(cell, change, bar)], weakest first."""
    s2 = max(fit.residual_variance, 1.0)
    bar = _price(problem, fit, candidates) + EVIDENCE
    model = Quadratic(problem, fit, np.zeros_like(fit.system.free))
    drops = sorted((m for m in model.moves(0.0, s2) if m[1][0] == "drop"),
                   key=lambda m: -m[0])
    found = []
    for k, (gain, move, keep) in enumerate(drops):
        if -gain >= bar:
            break
        if k >= limit:  # not refitted: the prediction stands
            found.append((move[1], float(-gain), float(bar)))
            continue
        try:
            trial = _exact_refit(problem, fit, model, keep,
                                 lambda _: fit.data_cost + s2 * bar)
            change = (trial.data_cost - fit.data_cost) / s2
        except BlowUp:  # without the term the system does not stay bounded: needed
            change = np.inf
        except Exception:  # noqa: BLE001 - the refit failed: not checked, a doubt
            change = np.nan
        if not change >= bar:  # NaN (refit failed) is a doubt too
            found.append((move[1], float(change), float(bar)))
    return found


def missing_terms(problem: Problem, fit: Fit, candidates, limit=MAX_ATTEMPTS):
    """Candidate terms left out of ``fit`` whose addition (the others refitted exactly)
    would change the criterion by less than ``MARGIN``: the data nearly call for them.

    Fails safe as :func:`weak_terms` does: the ``limit`` additions predicted best are
    refitted exactly; a further one predicted within the margin counts with its
    prediction. An addition whose refit blows up or fails is not counted (the system
    without the term stands). Returns [(cell, misfit change, price)], the term the
    data call for most (largest fall in misfit) first; the change is negative."""
    s2 = max(fit.residual_variance, 1.0)
    price = _price(problem, fit, candidates)
    allowed = candidates & ~fit.system.free
    if not allowed.any():
        return []
    model = Quadratic(problem, fit, allowed)
    adds = sorted(model.additions(price, s2), key=lambda m: -m[0])
    found = []
    for k, (gain, move, keep) in enumerate(adds):
        if -gain >= 2 * MARGIN:  # the quadratic model is good to a fraction of this
            break
        if k >= limit:
            if -gain < MARGIN:
                found.append((move[1], float(-gain - price), price))
            continue
        trial = _refit(problem, fit, model, keep)
        if trial is None:
            continue
        change = (trial.data_cost - fit.data_cost) / s2
        if change + price < MARGIN:
            found.append((move[1], float(change), price))
    return sorted(found, key=lambda f: f[1])


def _price(problem, fit, candidates):
    """The criterion's price of one term (see :func:`select_terms`)."""
    pool = int((candidates | fit.system.free).sum())
    return float(np.log(max(problem.n_data, 2)) + np.log(max(pool, 1)))


def _bic(fit, s2, price):
    return fit.data_cost / s2 + price * fit.system.n_free  # continuity penalty left out


def _refit(problem, fit, model, keep, line=None):
    """Exact fit with the coefficients ``keep`` (over the model's cells) free; None when
    it fails."""
    try:
        return _exact_refit(problem, fit, model, keep, line)
    except Exception:  # noqa: BLE001 - a move whose system blows up is not taken
        return None


def _exact_refit(problem, fit, model, keep, line=None):
    """Exact fit with the coefficients ``keep`` (over the model's cells) free.

    ``line(system)``, if given, is the data misfit (noise variances) the refit of
    ``system`` must get below to count (its move to win, its term to be weak, its
    exchange to be ambiguous): one still ``HOPELESS`` times above it after half its
    iterations, or after its first pass, gives up there, as a hypothesis's first fit
    does against the best (its verdict is the same unless the rest of the fit would
    have cut its misfit fifty-fold, or would have failed: a weak-term check then reads
    the term as needed, not as unchecked). On Hindmarsh-Rose at 5%, draw 9, term
    selection's refits crawled to their iteration limit 50-120 times above the line,
    two passes each."""
    system = fit.system
    free = np.zeros_like(system.free)
    coef = system.coef.copy()
    for on, cell, value in zip(keep, model.cells, model.values_after(keep), strict=True):
        free[cell] = on
        if on or system.free[cell]:
            coef[cell] = value
    new = ParametricSystem(system.state_names, system.n_observed, system.features, coef, free)
    give_up = np.inf if line is None else HOPELESS * max(line(new), 1.0) / degrees_of_freedom(
        problem.n_data, new, fit.starts)
    return problem.fit(new, fit.starts, give_up=give_up)
