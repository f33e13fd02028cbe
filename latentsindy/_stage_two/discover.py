"""Stage two: time-varying coefficients become hidden states of a closed system.

The pipeline: stage one (:class:`DynamicSINDy`) fits time-varying coefficients; its
varying terms, and alternatives to them, are proposed as structures
(:mod:`.hypotheses`); each is closed, refined by integration against the
observed data and scored on held-out segments (:mod:`.judge`); the best
small system wins and the others stay on the result (:mod:`.assemble`).
"""

from __future__ import annotations

import copy
import dataclasses
import inspect

import numpy as np

from .._core import recordings
from .._core import validation as val
from .._core.budget import budget, expired, spent, stamped
from .._core.derivatives import (
    AdaptiveSavitzkyGolay,
    noise_level,
)
from .._core.doubt import Doubt
from .._core.library import check_library, fit_library
from .._core.threads import single_thread
from .._core.timing import recording
from .._stage_one.estimator import DynamicSINDy
from . import context_build
from . import without_stage_one as blind_path
from .assemble import from_proposals, from_verdicts
from .fit.refine import RefineOptions
from .judge import judge_all
from .propose.hypotheses import propose
from .propose.proposal import evaluate, without_hidden
from .propose.smoother import Structure
from .result import HiddenDiscovery

VARIATION_SIGMAS = 3.0  # variation must exceed this many posterior std ...
VARIATION_RELATIVE = 0.05  # ... and this fraction of the coefficient's mean size
THRESHOLD = 0.05  # smallest share of an equation's RMS rate a constant term may explain
STAGE_ONE_SHARE = 0.5  # stage one also runs on segments at least this share of the longest
# Nested hidden states (:mod:`.nested`): tried only when the best system with one hidden
# state (or one and its rate) misses the data by far (``judge.NESTED_TRIGGER``).
NESTED = True


def discover_hidden(x_observed, library=None, *, t, feature_names=None, hidden_terms=None,
                    hidden_names=None, closure_library=None, generator="timevae",
                    generator_options=None, training=None, differentiation_method=None,
                    support=None, model=None, n_samples=64, refine=True, gaps="split",
                    outliers="discount", max_hidden=3, max_time=None, device="cpu",
                    seed=0, verbose=True) -> HiddenDiscovery:
    """Infer hidden variables and a closed, autonomous ODE from partial observations.

    Stage one fits time-varying coefficients Xi(t) (:class:`DynamicSINDy`); a
    coefficient that varies in time is a hidden state h in physical units (prey-only
    Lotka-Volterra: ``xdot = x h`` with ``h = alpha - beta y``). Because any state
    dependence can hide in a varying coefficient, discovery is a choice among
    structures: stage one's own, each library term as the carrier of the variation,
    varying coefficients that are affine images of one another as one hidden state,
    and (when no first-order law reproduces the data) a hidden state's rate as a
    second hidden state. Each structure's hidden series is estimated, closed by sparse
    regression, refined by integrating the closed system against the observed data
    (multiple shooting, torchdiffeq), its terms selected stepwise on that fit, and
    scored on held-out segments; the sparsest system that the held-out data do not
    reject against the best score wins (within one standard error of it, or not worse
    segment by segment). Structures with other hidden states that score as well (and
    are no larger, or are favoured by the held-out data) are reported as
    ``uncertain``, failed checks as ``doubts``; read ``confident``.

    Examples
    --------
    >>> import pysindy as ps
    >>> from latentsindy import discover_hidden, systems
    >>> data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=1000)
    >>> result = discover_hidden(data.x[:, :1], ps.PolynomialLibrary(degree=3),
    ...                          t=data.t, feature_names=["x"], verbose=False)
    >>> result.hidden_names, result.confident
    (('h0',), True)

    Parameters
    ----------
    x_observed : array (n_times, n_observed) or list of such arrays
        One or several recordings of the same system (lengths and sampling rates may
        differ). Rows with NaN are missing samples.
    library : pysindy feature library, optional
        Candidate functions for the observed equations (default polynomials of degree 2).
    t : float, array or list of arrays
        Sample spacing or sample times (any spacing: every step uses the actual times).
    feature_names : list of str, optional
        Names of the observed states (default ``x0, x1, ...``).
    hidden_terms : list of (state, feature), optional
        Fix the hidden states: each named coefficient is one hidden state (no search
        over carriers or shared variation; its rate may still be added as a second
        state, and terms are still selected).
    hidden_names : list of str, optional
        Names for the hidden states found, in order (default ``h0, h1, ...``; the rate
        of a hidden state ``h`` is ``h_rate``).
    closure_library : pysindy feature library, optional
        Candidates for the hidden equations (default polynomials of degree 2).
    generator, generator_options, training, differentiation_method, support
        Passed to :class:`DynamicSINDy`.
    model : DynamicSINDy, optional
        A configured stage one: every one of its parameters (``structure``,
        ``time_varying`` and the ones above included) is used, and ``library`` may then
        be left out. ``device``, ``seed`` and ``verbose`` of this call replace the
        model's, since they govern the whole discovery. Setting both ``model`` and one
        of the stage-one options above is an error. The model itself is not changed.
    n_samples : int
        Posterior samples of stage one's uncertainty band.
    refine : bool
        Refine every candidate system by integration and judge on held-out data
        (default). Off: candidates are ranked by their closure's held-out error and
        the coefficients come from the closure's integral fit.
    max_hidden : int
        At most this many hidden states in any structure judged (default 3): from
        shared variation, a hidden state's rate (needs 2), and a hidden state inside
        another's equation (needs 2; Lorenz seen through x: ``h1`` is the coefficient
        of x in ``dh0/dt``).
    gaps : {"split", "raise"}
        ``"split"`` (default): rows with missing values are dropped and a recording is
        split into segments at gaps (a time step 20 times the spacing around it); the
        segments share the law and each gets its own hidden initial values; segments
        under 16 samples are dropped with a note (:mod:`latentsindy._core.recordings`).
        ``"raise"``: missing values and gaps are an error.
    outliers : {"discount", "keep"}
        ``"discount"`` (default): isolated spikes (a single sample far off the curve of
        its neighbours while they lie on it, as a loose connector makes them) are
        replaced by their neighbours' curve before anything is fitted, and listed in
        ``data_use.discounted`` (:mod:`latentsindy._core.spikes`; white noise of any
        level and sharp features of the dynamics, which span several samples, are
        left alone). ``"keep"``: every sample as measured.
    max_time : float, optional
        Wall seconds for the whole call (default None, or infinity: no limit). Once
        they are spent, stage one's structure search fits no further neighbour (the
        step under way is not taken) and no adaptive priors, no alternative to stage
        one's own structure is proposed, and stage two starts no further hypothesis,
        term-selection step or fit iteration: the best system found so far is
        returned, with the doubt ``"time budget"`` saying what was not judged (so never
        ``confident``). Stage one's training (a fixed number of steps, seconds on most
        data, see ``timings``), its starting structures, the chosen structure's
        posterior and the fit under way always complete (the search keeps the
        training's second phase in reserve, and the call as much again for the result,
        whose refitting checks it then leaves out). A budget spent inside stage one's
        structure search (most of a slow call) leaves stage two no time to fit
        anything: the system returned is then an unchecked candidate, with the doubt
        ``"not checked"`` too. A call that left nothing out but ended past
        ``max_time`` has a note saying so, not the doubt. With ``verbose``, progress
        lines say which step runs, how many remain, and each step the budget leaves
        out.
    device : str
        Torch device for stage one's training and the refinement's integrations
        ("cpu", default, or "cuda"). A GPU pays off for long series in stage one; the
        refinement's batches are small, and on a GPU mostly wait on kernel launches
        (README, "Speed").
    seed : int
    verbose : bool

    Returns
    -------
    HiddenDiscovery
        Its ``timings`` say where the time went (wall seconds by stage).
    """
    stage_one = _stage_one_params(model, library=library, generator=generator,
                                  generator_options=generator_options, training=training,
                                  differentiation_method=differentiation_method,
                                  support=support)
    max_time = val.check_seconds(max_time, "max_time")
    with recording() as seconds, budget(max_time, verbose) as state:
        result = _discover(x_observed, t, feature_names, hidden_terms, hidden_names,
                           closure_library, stage_one, n_samples, refine, gaps, outliers,
                           max_hidden, device, seed, verbose)
    result = stamped(result, state)  # what max_time left out: a doubt
    return dataclasses.replace(result, timings=dict(seconds))


# the stage-one options discover_hidden takes itself, with their defaults (its signature's)
_STAGE_ONE_DEFAULTS = {
    name: inspect.signature(discover_hidden).parameters[name].default
    for name in ("library", "generator", "generator_options", "training",
                 "differentiation_method", "support")}


def _unset(name, value, model) -> bool:
    """Whether option ``name`` was left at its default (or, for the library, is the
    model's own)."""
    default = _STAGE_ONE_DEFAULTS[name]
    if name == "library" and value is model.library:
        return True
    return value is default or (isinstance(default, str) and value == default)


def _stage_one_params(model, **given) -> dict:
    """Stage one's constructor parameters, from ``model`` or from the options given (not
    both), without ``device``, ``seed`` and ``verbose`` (the discovery's own)."""
    if model is None:
        return given
    if not isinstance(model, DynamicSINDy):
        raise TypeError(f"model must be a DynamicSINDy (configured, not necessarily fitted); "
                        f"got {type(model).__name__}.")
    clash = sorted(k for k, v in given.items() if not _unset(k, v, model))
    if clash:
        raise ValueError(f"{clash} set both here and by model=; set stage one's options on "
                         "the DynamicSINDy you pass (model.set_params(...)), or leave model "
                         "out.")
    params = model.get_params()
    return {k: v for k, v in params.items() if k not in ("device", "seed", "verbose")}


def _discover(x_observed, t, feature_names, hidden_terms, hidden_names, closure_library,
              stage_one, n_samples, refine, gaps, outliers, max_hidden, device, seed,
              verbose):
    library, support = stage_one["library"], stage_one["support"]
    differentiation_method = stage_one["differentiation_method"]
    segments, seg_times, use = recordings.split(x_observed, t, gaps=gaps, outliers=outliers)
    # the longest segment first: stage one's coefficients (and the result's first
    # trajectory) come from it
    order = [int(np.argmax([len(x) for x in segments]))]
    order += [k for k in range(len(segments)) if k != order[0]]
    trajs, times = [segments[k] for k in order], [seg_times[k] for k in order]
    use = use.reordered(order)
    names = val.check_feature_names(feature_names, trajs[0].shape[1])
    closure_library = check_library(closure_library, "closure_library")
    val.check_positive(n_samples, "n_samples", integer=True)
    val.check_positive(max_hidden, "max_hidden", integer=True)
    device = val.check_device(device)
    if not isinstance(refine, bool):
        raise TypeError(f"refine must be True or False; got {refine!r}.")
    _, features = fit_library(check_library(library), trajs[:1], names)
    _check_hidden_request(hidden_terms, hidden_names, names, features)

    # Stage one on the longest segment, and on every segment at least half as long:
    # hidden states differ between segments, and the evidence that a coefficient varies
    # is pooled over them. Later segments reuse the first one's support so the
    # equations are shared; shorter segments enter stage two only.
    if differentiation_method is None and len(trajs) > 1:
        # one noise level for every segment (the model stage two fits): a short
        # segment's own estimate is rough, and the differentiator's window hangs on it
        differentiation_method = AdaptiveSavitzkyGolay(noise_std=noise_level(trajs, times))
    fits, coefs = [], []
    panel = len(trajs[0]) < val.MIN_TIMES  # no recording long enough for stage one
    if panel:
        model, first = blind_path.stand_in(trajs, times, names, features,
                                           copy.deepcopy(check_library(library)),
                                           differentiation_method)
        fits, coefs = [model], [first]
    for k, (x, tk) in enumerate(zip(trajs, times, strict=True)):
        if panel or len(x) < STAGE_ONE_SHARE * len(trajs[0]):
            continue
        model = DynamicSINDy(**(stage_one | {
            "differentiation_method": differentiation_method,
            "support": support if k == 0 else fits[0].support_}),
            device=device, verbose=verbose, seed=seed)
        fits.append(model.fit(x, tk, feature_names=names))
        coefs.append(model.coefficients(n_samples=n_samples))
    first = coefs[0]
    pairs = _varying(coefs, hidden_terms)
    ctx = (context_build.bare(fits[0].library_, trajs, times, names, features,
                              closure_library, support, THRESHOLD) if panel
           else context_build.build(fits[0], trajs, times, names, first, closure_library,
                                    support, THRESHOLD))
    index = [(names.index(s), first.feature_names.index(f)) for s, f in pairs]
    blind = False  # stage one saw no law where the data move
    alone = False  # the law without hidden states judged alone, carriers on its score
    if not pairs:  # the observed states close on their own, or no law is found
        proposals = [without_hidden(first.support, ctx)]
        if hidden_terms is None and (panel or blind_path.misfit(
                proposals[0], ctx, refine, device) > blind_path.MOVES):
            # they do not close on their own: stage two looks for a hidden carrier itself
            ctx, proposals, blind = blind_path.with_carriers(
                ctx, proposals, first.support, fits[0].library_, panel, refine)
        else:
            alone = hidden_terms is None
    elif hidden_terms is None:
        series = np.stack([np.concatenate([c.term(s, f) for c in coefs]) for s, f in pairs],
                          axis=1)
        proposals = propose(ctx, first.support, index, series, fuller=refine,
                            max_rank=max_hidden)
    else:
        proposals = [evaluate(_named_structure(first.support, index), ctx, "hidden_terms")]
    if refine:
        with single_thread():
            ordered, uncertain = judge_all(proposals, ctx, RefineOptions(device=device), max_hidden,
                                           NESTED, blind=bool(blind))
            if alone and not blind_path.reproduced(ordered) and not spent(blind_path.BESIDE):
                more = blind_path.with_carriers(ctx, proposals, first.support,
                                                fits[0].library_, panel, refine)
                again = judge_all(more[1], more[0], RefineOptions(device=device), max_hidden,
                                  NESTED, blind=bool(more[2]))
                # (where max_time left the second without a scored winner, the first stands)
                if (again[0] and again[0][0].scored) or not (ordered and ordered[0].scored):
                    (ctx, proposals, blind), (ordered, uncertain) = more, again
            if ordered:
                result = from_verdicts(ordered, uncertain, ctx, first, hidden_names,
                                       blind_path.note(panel) if blind else None)
    stds = {ij: first.std[:, ij[0], ij[1]] for ij in index}
    if refine and not ordered:  # an answer, unchecked and saying so, not an exception
        result = from_proposals(proposals, ctx, first, hidden_names, stds)
        result = dataclasses.replace(result, doubts=(Doubt(
            "not checked", f"none of the {len(proposals)} candidate closed systems could "
            "be fitted by integration (each blew up or failed from its estimated hidden "
            f"series; varying terms {pairs}): the system shown is the candidate whose "
            "hidden states' equations best match stage one's estimated series, unchecked. "
            "The library may lack the terms that carry the hidden state (a constant: "
            "include_bias=True), or the closure_library those of its law; or the samples "
            "are too few per cycle") if not expired() else Doubt(
            "not checked", "max_time was spent before any candidate closed system was "
            "fitted by integration: the system shown is the candidate whose hidden "
            "states' equations best match stage one's estimated series, unchecked"),))
    elif not refine:
        result = from_proposals(proposals, ctx, first, hidden_names, stds)
    if not any(term.value != 0 for term in result.terms):
        result = dataclasses.replace(result, doubts=result.doubts + (Doubt(
            "no law", "no law was found: no term of the library was kept in any equation "
            "(the derivatives are too noisy, or the samples too few per oscillation, to "
            "show one); the data are described as constant"),))
    notes = use.dropped
    if blind:
        notes += (blind_path.note(panel),)
        full = blind_path.saturated(ordered[0]) if refine and ordered else []
        if full:
            result = dataclasses.replace(result, doubts=result.doubts + (blind_path.doubt(
                panel, [result.hidden_names[a] for a in full]),))
    if hidden_names is not None and len(hidden_names) != len(result.hidden_names):
        notes += (f"{len(hidden_names)} hidden_names given for {len(result.hidden_names)} "
                  f"hidden state(s) found; names used: {list(result.hidden_names)}",)
    return dataclasses.replace(result, notes=result.notes + notes, data_use=use)


def _named_structure(support, index):
    """One hidden state per named coefficient."""
    sup = np.array(support, dtype=bool, copy=True)
    loads = np.zeros((*sup.shape, len(index)))
    for a, (i, k) in enumerate(index):
        sup[i, k] = True
        loads[i, k, a] = 1.0
    return Structure(sup, loads, tuple(index))


def _check_hidden_request(hidden_terms, hidden_names, states, features):
    """Validate hidden_terms / hidden_names before any training."""
    if hidden_terms is not None:
        pairs = []
        for p in hidden_terms:
            if (not isinstance(p, list | tuple) or len(p) != 2 or p[0] not in states
                    or p[1] not in features):
                raise ValueError(
                    f"hidden_terms entries must be (state, feature) pairs with state in "
                    f"{list(states)} and feature in {list(features)}; got {p!r}.")
            pairs.append(tuple(p))
        if len(set(pairs)) != len(pairs):
            raise ValueError(f"hidden_terms has duplicates: {pairs}.")
        if hidden_names is not None and len(hidden_names) != len(pairs):
            raise ValueError(f"hidden_names has {len(hidden_names)} name(s) but "
                             f"{len(pairs)} hidden state(s) were requested in hidden_terms.")
    if hidden_names is not None:
        names = val.check_feature_names(hidden_names, len(hidden_names), "hidden_names")
        clash = set(names) & set(states)
        if clash:
            raise ValueError(f"hidden_names {sorted(clash)} clash with the observed state names.")


def _varying(coefs, hidden_terms):
    """Stage one's varying coefficients (or the named ones), most significant first.

    With several segments the evidence is pooled: a coefficient varies when its series
    over all of them (within and between segments) varies beyond the posterior spread.
    A hidden state need not move in every segment: a transient is flat before and after
    it, and a recording that holds only its start shows a constant, at another level
    than the next one's."""
    first = coefs[0]
    if hidden_terms is not None:
        pairs = [tuple(p) for p in hidden_terms]
        active = set(first.active_terms())
        for p in pairs:
            if p not in active:
                raise ValueError(f"hidden term {p!r} was removed by the sparsity stage "
                                 f"(active terms: {sorted(active)}); fix it with support=.")
        return pairs
    found = []
    for s, f in first.active_terms():
        mean = np.concatenate([c.term(s, f) for c in coefs])
        std = np.concatenate([c.term_std(s, f) for c in coefs])
        if _varies(mean, std):
            found.append((float(np.std(mean)) / max(float(np.mean(std)), 1e-300), (s, f)))
    found.sort(key=lambda item: -item[0])
    return [p for _, p in found]


def _varies(mean, std):
    variation = float(np.std(mean))
    return (variation > VARIATION_SIGMAS * float(np.mean(std))
            and variation > VARIATION_RELATIVE * float(np.mean(np.abs(mean))))
