"""Which terms exist and which of them vary, decided together by the evidence.

A generator's variation is flexible enough to stand in for a missing term (Lorenz's
``rho(t) x`` absorbing ``-y``, a rough coefficient following the states), so its own
support and variation are only a proposal. Here each free equation's structure (the
support S and the varying terms V in it) is chosen by the exact evidence of the
varying-coefficient model (:mod:`.vcm_fit`) on the integral form of the data
(:mod:`.vcm`), with a prior that charges a Bayes factor of 20 for every term and for
every variation:

* a structure is admissible when every term explains at least ``threshold`` of its
  equation's RMS derivative (mean |coefficient| in normalised units, the generators'
  pruning rule) and every variation does too (its standard deviation over time);
  a candidate is made admissible by freezing the smallest variation, or dropping the
  smallest term, until it is;
* a greedy search moves one step at a time (add a constant term, drop a term, freeze
  or free a term's variation) to the best admissible neighbour while that raises the
  score (from more than ``DESCENT`` varying terms, first to the best with one variation
  frozen); it starts from the generator's structure, from the generator's support with
  every term constant, and from a sequentially thresholded constant fit, so a
  generator that lost a term does not decide the outcome;
* with Gaussian slope priors first (fast), then again with adaptive ones (a sharp
  switch is one bend, not a rough series) from the best of the structures found, and
  also from another of them where it starts higher with adaptive priors: the better
  end is taken, and where the two ends differ the other is kept (the evidence has two
  optima: a doubt, and the band holds both).

The result per equation is an :class:`EquationChoice`: the chosen fit and the
admissible neighbours that score within that Bayes factor (the structure is then
uncertain: the band includes them, and they become doubts).
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass

import numpy as np

from .._core.budget import expired, passed, progress, reserving, spent
from .._core.parallel import available, forked_map
from .._core.threads import single_thread
from .vcm_fit import EM_STEPS, EquationFit, EquationModel

LOG_PRIOR_ODDS = np.log(20.0)  # price of one more term, or one more varying term
# A climbing step expected to take this long (s, at the last pace) goes to two processes
SIDE_BY_SIDE = 0.15
# A climbing step expected to take this long (seconds) is announced in the progress lines
ANNOUNCE = 1.0
# A climb at more varying terms than this sheds them: its step fits the v structures
# with one variation frozen (a fit costs ~v^3), the full step only where none scores higher
DESCENT = 3
_PRIORS = {False: "Gaussian", True: "adaptive"}
# what the discovery's max_time leaves out when it runs out during the search
_STOPPED = "stage one's structure search (stopped where it was)"
# and before the adaptive priors (a fit of many varying terms: seconds): Gaussian ones stand
GAUSSIAN = "stage one's adaptive slope priors (Gaussian ones used)"


@dataclass(frozen=True)
class EquationChoice:
    """The structure chosen for one equation, and its close competitors."""

    fit: EquationFit
    rivals: tuple[EquationFit, ...]  # admissible neighbours scoring within the price
    searched: int  # structures evaluated
    # where the adaptive climbs from two starts ended at different structures, the end
    # not taken: the evidence's local optima disagree, so the structure is uncertain
    apart: tuple[EquationFit, ...] = ()


def penalised(fit: EquationFit) -> float:
    """Score of a structure: log evidence minus the price of its terms and variations."""
    return fit.score - LOG_PRIOR_ODDS * (len(fit.support) + len(fit.varying))


class StructureSearch:
    """Greedy search over (support, varying) of one equation.

    Parameters
    ----------
    model : EquationModel
    basis : (first, values) of the spline basis at the samples (for term sizes)
    threshold : float
        Smallest normalised size of a term, and of a variation.
    free : bool
        Whether the support may change (False: the user fixed this equation).
    support : set of int
        The support to keep when not ``free``.
    allowed : set of int
        Terms that may vary.
    """

    def __init__(self, model: EquationModel, basis, threshold, free, support, allowed,
                 label="the equation"):
        self.model, self.basis, self.threshold = model, basis, threshold
        self.label = label  # what the progress lines call the equation
        self.pace = {}  # seconds per admissible fit lately, Gaussian (False) and adaptive
        self.free, self.fixed_support, self.allowed = free, set(support), set(allowed)

    def sizes(self, fit):
        """Mean |coefficient| of every term and standard deviation of every variation."""
        mean, _ = fit.series(*self.basis, with_sd=False)
        size = {k: float(np.mean(np.abs(mean[:, a]))) for a, k in enumerate(fit.varying)}
        spread = {k: float(np.std(mean[:, a])) for a, k in enumerate(fit.varying)}
        size.update({j: abs(float(c)) for j, c in zip(fit.constant, fit.constants,
                                                        strict=True)})
        return size, spread

    def admissible(self, support, varying, adaptive, start=None):
        """Freeze the smallest variation, else drop the smallest term, until every one
        passes the threshold; returns the fit. ``start``: a neighbour's fit (its
        roughness is the starting point)."""
        support, varying = set(support), set(varying) & set(support) & self.allowed
        rough = {} if start is None else dict(zip(start.varying, start.log_rough, strict=True))
        while True:
            fit = self.model.fit(support, varying, adaptive, rough)
            if not np.isfinite(fit.score):
                return fit
            size, spread = self.sizes(fit)
            small = [k for k in varying if spread[k] < self.threshold]
            if small:
                varying.discard(min(small, key=spread.get))
                continue
            small = [k for k in support if size[k] < self.threshold] if self.free else []
            if small:
                k = min(small, key=size.get)
                support.discard(k)
                varying.discard(k)
                continue
            return fit

    def earned(self, fit, proposed):
        """Drop added constants that a varying term could carry instead.

        With a varying term in the equation any state dependence can be moved between
        the variation and constant terms (x^2 c + h(t) x = (c x + h(t)) x), and the
        smoothness prior always rewards a little of that: a hidden state's variation
        is never smooth in time, and subtracting a state function from it smooths it
        a bit (prey-only Lotka-Volterra, 8000 samples: x^2 and x^3 added for a gain
        of 27 nats, the variation's effective degrees of freedom 223 -> 212). A
        constant the generator did not propose stays only if removing it at least doubles
        the variation's degrees of freedom (it restored a term the variation had absorbed:
        x z behind rho(t) x) or raises the misfit by 10% (-y behind rho(t) x)."""
        if not self.free or not fit.varying:
            return fit
        while True:
            cheap = []
            for j in fit.constant:
                if j in proposed:
                    continue
                if spent(_STOPPED, ahead=self.pace.get(fit.adaptive, 0.0)):  # at the pace
                    return fit
                alt = self.model.fit(set(fit.support) - {j}, fit.varying, fit.adaptive)
                if np.isfinite(alt.score) and not _earns(fit, alt):
                    cheap.append(alt)
            if not cheap:
                return fit
            fit = max(cheap, key=penalised)

    def _is_rival(self, other, fit, proposed):
        """A neighbour that scores within the price, and does not merely add a
        constant the variation could carry (see :meth:`earned`)."""
        if same_structure(other, fit):
            return False
        if penalised(other) <= penalised(fit) - LOG_PRIOR_ODDS:
            return False
        added = set(other.constant) - set(fit.support) - set(proposed)
        return not (added and fit.varying and self.free and not _earns(other, fit))

    def neighbours(self, fit, shed=False):
        """The structures one step away; with ``shed``, only those with one variation
        frozen (a descent from many varying terms, see ``DESCENT``)."""
        support, varying = set(fit.support), set(fit.varying)
        if shed:
            return [(support, varying - {k}) for k in sorted(varying)]
        out = []
        if self.free:
            n_features = self.model.g.n_features
            out += [(support | {j}, varying) for j in range(n_features) if j not in support]
            out += [(support - {k}, varying - {k}) for k in support]
        out += [(support, varying - {k}) for k in varying]
        out += [(support, varying | {k}) for k in support - varying if k in self.allowed]
        return out

    def climb(self, fit, adaptive):
        """Greedy ascent from ``fit``; returns the last fit and its neighbours' fits
        (none where the discovery's ``max_time`` ran out: the ascent stops there)."""
        seconds = self.pace.get(adaptive, 0.0)  # per neighbour, at the last step's pace
        shed = len(fit.varying) > DESCENT
        for number in itertools.count(1):  # the climb's steps, for the progress lines
            if spent(_STOPPED):
                return fit, []
            step = self.neighbours(fit, shed)
            if seconds * len(step) >= ANNOUNCE:
                progress(f"stage one's structure search, {self.label}, climbing step "
                         f"{number}: {len(step)} neighbours to fit with "
                         f"{_PRIORS[adaptive]} priors, about {seconds * len(step):.0f} s")
            begin = time.perf_counter()
            with reserving(seconds):  # max_time: a neighbour starts if it can end in time
                near, ran = fit_structures(self, step, adaptive, fit, seconds)
            if near is None:  # max_time ran out during the step: it is not taken
                passed(_STOPPED)  # (the reserve may have stopped it: spent() says no)
                return fit, []
            seconds = (time.perf_counter() - begin) * ran / max(len(step), 1)
            self.pace[adaptive] = seconds
            best = max(near, key=penalised, default=None)
            if best is None or penalised(best) <= penalised(fit) + 1e-9:
                if shed:  # no frozen variation scores higher: the full step
                    shed = False
                    continue
                return fit, near
            fit, shed = best, len(best.varying) > DESCENT

    def _adaptive_climbs(self, best, found):
        """The adaptive climb from the Gaussian search's best structure and, where
        another of the searches' optima scores higher with adaptive priors at its start,
        from that one too; returns the higher end (the first on a tie).

        The Gaussian ranking can pick the wrong basin (Rucklidge's system at 1% noise:
        a varying constant and y^2, which absorb anything, beat the true x and varying y
        by 80 nats with Gaussian slope priors and lose by 143 with adaptive ones), but
        a start that scores higher is not a higher end either: Lorenz with a switching
        sigma (the paper's case, seeds 1 and 2, with line searches of 20 trials) went
        from the better start (x constant, y and z varying) to a wrong local optimum,
        below where the Gaussian best's climb ends (the truth; with 8 trials, since
        bd88477, the Gaussian best is the truth at both seeds). Noisy roughness searches
        can still leave a climb short, so both climbs, the better end taken; the Gaussian best's
        climb runs first, on the cache as it was, and where no other optimum starts
        higher the fits made to rank them leave the cache: there the search is the
        same as a single climb, fit for fit.

        Returns ``(fit, near, other)``: the higher end, its neighbours, and the other
        end where the two climbs ended at different structures (else None). Where the
        discovery's ``max_time`` has run out: ``best`` (no neighbours, no other)."""
        # max_time: an adaptive fit runs to its end, EM_STEPS searches at the Gaussian pace
        if spent(GAUSSIAN, ahead=EM_STEPS * self.pace.get(False, 0.0)):
            return best, [], None
        begin = time.perf_counter()
        chosen = self.admissible(best.support, best.varying, True)
        self.pace[True] = time.perf_counter() - begin  # an adaptive climb's first pace
        ends = [self.climb(chosen, True)]
        others = []
        for f in found:
            if not any(same_structure(f, o) for o in [best, *others]):
                others.append(f)
        if not others or spent(_STOPPED):
            return (*ends[0], None)
        cache = dict(self.model._cache)
        fits = fit_structures(self, [(f.support, f.varying) for f in others], True,
                              None, self.pace[True])[0]
        if fits is None:  # max_time ran out among them: no rival climb
            passed(_STOPPED)
            self.model._cache = cache
            return (*ends[0], None)
        rival = max(fits, key=penalised)
        if penalised(rival) <= penalised(chosen):
            self.model._cache = cache
            return (*ends[0], None)
        ends.append(self.climb(rival, True))
        (fit, near), (other, _) = sorted(ends, key=lambda end: -penalised(end[0]))
        return fit, near, None if same_structure(other, fit) else other

    def run(self, starts, proposed=()) -> EquationChoice:
        """Search from every (support, varying) in ``starts``, Gaussian then adaptive;
        constants outside ``proposed`` (the generator's support) must then earn their
        place (:meth:`earned`)."""
        if not self.free:
            starts = [(self.fixed_support, v) for _, v in starts]
        found = []
        for s, v in starts:
            begin = time.perf_counter()
            start = self.admissible(s, v, False)
            # the start's own fit paces its first step where it took longer than the
            # last step's fits (a start with many varying terms: its neighbours have
            # as many, give or take one); a start found cached says nothing
            self.pace[False] = max(self.pace.get(False, 0.0), time.perf_counter() - begin)
            found.append(self.climb(start, False)[0])
        best = max(found, key=penalised)
        fit, near, other = self._adaptive_climbs(best, found)
        proposed = set(proposed)
        reduced = self.earned(fit, proposed)
        if reduced is not fit:  # its neighbours, with its priors (max_time: at their pace)
            fit = reduced
            with reserving(seconds := self.pace.get(fit.adaptive, 0.0)):
                near = [] if spent(_STOPPED) else fit_structures(
                    self, self.neighbours(fit), fit.adaptive, fit, seconds)[0]
            if near is None:  # max_time ran out among them
                passed(_STOPPED)
                near = []
        rivals = tuple(f for f in near if self._is_rival(f, fit, proposed))
        # the other climb's end, unless it is the choice or among its rivals already
        apart = () if other is None or any(same_structure(other, f)
                                           for f in (fit, *rivals)) else (other,)
        return EquationChoice(fit, rivals, len(self.model._cache), apart)


def same_structure(a, b) -> bool:
    """Whether two fits have the same structure (support and varying terms)."""
    return (a.support, a.varying) == (b.support, b.varying)


def _earns(fit, without):
    """Whether a constant that ``fit`` has and ``without`` lacks earns its place: without
    it the variation needs at least twice the degrees of freedom, or the misfit rises
    by 10%."""
    return (float(np.sum(without.edf)) >= 2.0 * float(np.sum(fit.edf))
            or without.noise_variance >= 1.1 * fit.noise_variance)


def fit_structures(search: StructureSearch, step, adaptive, start, seconds):
    """``(fits, processes used)``: side by side where two or more structures take
    ``SIDE_BY_SIDE`` seconds at ``seconds`` each, else in turn; the same fits."""
    if len(step) > 1 and seconds * len(step) >= SIDE_BY_SIDE:
        return side_by_side(search, step, adaptive, start)
    return in_turn(search, step, adaptive, start), 1


def in_turn(search: StructureSearch, step, adaptive, start):
    """``[search.admissible(s, v, adaptive, start) for s, v in step]``, one neighbour
    after the other; None where the discovery's ``max_time`` runs out before the last
    one (a step over many varying terms can take tens of seconds: the budget is asked
    before each neighbour)."""
    near = []
    for s, v in step:
        if expired():
            return None
        near.append(search.admissible(s, v, adaptive, start))
    return near


def side_by_side(search: StructureSearch, step, adaptive, start):
    """``[search.admissible(s, v, adaptive, start) for s, v in step]``, the neighbours
    of one climbing step fitted by two processes where a second core is to be had
    (:func:`.._core.parallel.forked_map`), with the same fits and the same cache as the
    loop gives; returns (fits, processes used), or (None, processes used) where the
    discovery's ``max_time`` runs out before every neighbour is fitted (the cache is then
    as it was before the step; :func:`in_turn` keeps the fits it made).

    A neighbour's fits are the loop's when every structure it asked for
    (``EquationModel.looked``) was cached or not as in the loop, and each one cached
    was the same fit: made before the step, or by the same earlier neighbour, whose own
    fits were the loop's. Otherwise (it fitted a structure itself that an earlier
    neighbour had fitted in the other process, from another start) it is fitted again,
    here, in the loop's order; the cache is rebuilt in that order, neighbour by
    neighbour.
    """
    with single_thread():  # torch and the BLAS on one thread, in both processes
        return _side_by_side(search, step, adaptive, start)


def _side_by_side(search, step, adaptive, start):
    model = search.model
    if not available(len(step)):
        return in_turn(search, step, adaptive, start), 1
    before = dict(model._cache)
    made_by = dict.fromkeys(before, -1)  # in each process: which neighbour fitted what

    def one(k):  # the fit, the structures asked for (and who had fitted them), new fits
        if expired():  # max_time: the step is not taken
            return None
        model.looked, known = [], set(model._cache)
        try:
            fit = search.admissible(*step[k], adaptive, start)
            new = {key: f for key, f in model._cache.items() if key not in known}
            looked = [(key, made_by[key] if key in known else None) for key in model.looked]
            made_by.update(dict.fromkeys(new, k))
            return _key(fit), looked, new
        finally:
            model.looked = None

    outcomes = forked_map(one, range(len(step)), paced=False)  # SIDE_BY_SIDE decided
    if any(outcome is None for outcome in outcomes):
        model._cache = before
        return None, 2
    cache, fits = dict(before), []
    model._cache = cache  # the loop's cache, rebuilt in its order
    maker = dict.fromkeys(before, -1)  # who fitted each structure in the loop's order
    kept = {-1}  # neighbours whose own fits are the loop's
    for k, (key, looked, new) in enumerate(outcomes):
        if all(maker.get(asked) == by and by in kept if by is not None else asked not in cache
               for asked, by in looked):
            cache.update(new)
            maker.update(dict.fromkeys(new, k))
            kept.add(k)
            fits.append(cache[key])
            continue
        if expired():
            model._cache = before
            return None, 2
        known = set(cache)
        fits.append(search.admissible(*step[k], adaptive, start))
        maker.update(dict.fromkeys((key for key in cache if key not in known), k))
    return fits, 2


def _key(fit: EquationFit):
    """The cache key of a fit (``EquationModel.fit``)."""
    return (fit.support, fit.varying, fit.adaptive)
