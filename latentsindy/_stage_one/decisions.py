"""Discrete term decisions between the support phase and the refit.

The relaxed penalties of the support phase (log-L1 on sizes, relaxed-L0 gates on time
variation) leave three kinds of wrong decisions that least-squares checks on the fitted
coefficients correct:

* :func:`freeze_constant_terms`: a term whose time variation explains no more than its
  cost is fitted as a constant (backward elimination of variation);
* :func:`restore_terms`: a pruned term that the residual still needs comes back as a
  constant (forward selection of terms);
* :func:`restore_absorbed_terms`: a pruned term whose role a varying coefficient has
  absorbed comes back as a constant.

Then, by default, the exact varying-coefficient model decides (:mod:`.structure`):
:func:`adopt_structure` sets every equation's support and varying terms to its choice
and pins the constants at its estimates; the generator's refit learns the variation.

All accumulate normal equations block by block, so memory does not depend on the
series length.
"""

from __future__ import annotations

import torch


@torch.no_grad()
def freeze_constant_terms(model, theta, xdot, weights, inputs, cost, free_rows):
    """Backward step on time variation: fit as constants the terms whose variation does
    not pay for itself.

    For every free equation ``i``, a weighted least-squares fit of ``xdot_i`` on every
    library column (as constants) plus one column ``theta_k(t) Xi_ik(t)`` per varying
    term ``k`` (the variation as the model fitted it, with a free scale) measures what
    each term's variation explains beyond any constant term. Greedily, the term whose
    variation explains least is frozen while that share of the weighted mean squared
    misfit is below ``cost`` (in the training loss's units: the price of a varying
    term). A frozen term keeps its time-mean coefficient. Returns the frozen
    (equation, term) pairs.

    Without this step a term whose variation is not needed keeps it: the variation
    absorbs part of a constant term's role (Lorenz's ``rho(t)`` mimicking ``-y``), and
    the constants come out biased.
    """
    n_states, n_features = model.support.shape
    varying = (model.time_varying > 0) & model.support
    rows = [i for i in range(n_states) if bool(free_rows[i]) and bool(varying[i].any())]
    if not rows:
        return []
    gram, cross, total = _augmented_normal_equations(model, theta, xdot, weights, inputs, rows)
    n_obs = theta.shape[0] * theta.shape[1]
    constants = list(range(n_features))
    frozen = []
    for i in rows:
        kept = torch.nonzero(varying[i]).flatten().tolist()
        while kept:
            full = _explained(gram[i], cross[i], constants + [n_features + k for k in kept])[0]
            loss = {k: full - _explained(gram[i], cross[i], constants + [
                n_features + m for m in kept if m != k])[0] for k in kept}
            k = min(loss, key=loss.get)
            if loss[k] / n_obs >= cost:
                break
            kept.remove(k)
            model.freeze_constant(i, k, float(total[i, k]) / theta.shape[1])
            frozen.append((i, k))
    return frozen


def _augmented_normal_equations(model, theta, xdot, weights, inputs, rows):
    """Weighted normal equations of xdot_i on [theta(t), theta(t) * Xi_i(t)] (2F columns)
    for the equations in ``rows``, and the time sums of Xi, accumulated block by block."""
    n_states, n_features = model.support.shape
    like = dict(dtype=torch.float64, device=theta.device)
    width = 2 * n_features
    gram = torch.zeros(n_states, width, width, **like)
    cross = torch.zeros(n_states, width, **like)
    total = torch.zeros(n_states, n_features, **like)
    for lo, hi, xi in model.mean_blocks(inputs):
        th = theta[:, lo:hi].double()
        w = weights[:, lo:hi].double()
        xi = xi.double()
        total += xi.sum(dim=0)
        for i in rows:
            z = torch.cat([th, th * xi[None, :, i]], dim=-1).reshape(-1, width)
            wi = w[..., i].reshape(-1, 1)
            gram[i] += z.T @ (z * wi)
            cross[i] += z.T @ (wi[:, 0] * xdot[:, lo:hi, i].double().reshape(-1))
    return gram, cross, total


@torch.no_grad()
def restore_absorbed_terms(model, theta, xdot, weights, inputs, threshold, free_rows,
                           min_share=0.5):
    """Forward step for terms hidden inside a varying coefficient.

    Any state dependence can be absorbed into a time-varying coefficient: with both
    states of Lotka-Volterra observed and a drifting alpha(t), ``xdot = c(t) x`` with
    ``c(t) = alpha(t) - beta y(t)`` fits as well as ``alpha(t) x - beta x y`` and has
    one term fewer, so the sparsity phase can prefer it. Neither the residual (there
    is none) nor the variation test (the variation is real) sees that. Here the
    contribution ``theta_k(t) Xi_k(t)`` of every varying term is regressed on its own
    column and one pruned column ``theta_j`` (constants): a column that explains at
    least ``min_share`` of the contribution's variation beyond its own column, with a
    normalised coefficient >= ``threshold``, is restored as a constant with that
    coefficient (on that example: 93% explained, and beta within 9%; on prey-only LV,
    where the variation is a hidden state, x^2 and x^3 explain 0.1%). The refit then
    re-learns the smaller variation. Returns the restored (equation, term) pairs.
    """
    n_states, n_features = model.support.shape
    varying = (model.time_varying > 0) & model.support
    rows = [i for i in range(n_states) if bool(free_rows[i]) and bool(varying[i].any())
            and not bool(model.support[i].all())]
    if not rows:
        return []
    gram = _augmented_normal_equations(model, theta, xdot, weights, inputs, rows)[0]
    restored = []
    for i in rows:
        g, taken = gram[i], []
        while True:
            best = None
            pruned = torch.nonzero(~model.support[i]).flatten().tolist()
            for k in torch.nonzero(varying[i]).flatten().tolist():
                c = n_features + k
                own = _unexplained(g, c, [k] + taken)[0]
                if own <= 1e-12 * float(g[c, c]):
                    continue
                for j in pruned:
                    left, fit = _unexplained(g, c, [k] + taken + [j])
                    share = 1.0 - left / own
                    if share >= min_share and abs(float(fit[-1])) >= threshold and (
                            best is None or share > best[0]):
                        best = (share, j, fit[1:])
            if best is None:
                break
            _, j, fit = best
            taken.append(j)
            model.restore_constant(i, j)
            model.constants[i, taken] = fit.to(model.constants.dtype)
            restored.append((i, j))
    return restored


def _unexplained(gram, target, cols):
    """Weighted sum of squares of column ``target`` left after a least-squares fit on
    ``cols`` (indices into the same normal equations), and the fit."""
    explained, fit = _explained(gram, gram[:, target], cols)
    return float(gram[target, target]) - explained, fit


@torch.no_grad()
def restore_terms(model, theta, xdot, weights, inputs, threshold, free_rows,
                  min_gain=0.25):
    """Forward step after the support phase: return pruned terms that the data need.

    The sparsity penalty trades a term's size against the misfit its removal causes;
    when the term is nearly collinear with others (Lorenz's ``-y`` against ``rho x``)
    that misfit is small in absolute terms and a real term can be dropped. Here each
    pruned free term is offered back, equation by equation, greedily: a weighted least
    squares fit of the residual on the active terms plus the candidate (constant
    corrections) must give the candidate a normalised size >= ``threshold`` and cut the
    misfit left after the active terms' own corrections by at least ``min_gain`` (a
    share, so the test does not depend on units or noise level). Restored terms are
    constants. Accumulates normal equations block by block (memory independent of T).
    Returns the restored (equation, term) pairs.
    """
    n_states, n_features = model.support.shape
    like = dict(dtype=torch.float64, device=theta.device)
    gram = torch.zeros(n_states, n_features, n_features, **like)
    cross = torch.zeros(n_states, n_features, **like)
    misfit = torch.zeros(n_states, **like)
    for lo, hi, xi in model.mean_blocks(inputs):
        th = theta[:, lo:hi].double()
        w = weights[:, lo:hi].double()
        r = xdot[:, lo:hi].double() - torch.einsum("btf,tnf->btn", th, xi.double())
        flat = th.reshape(-1, n_features)
        for i in range(n_states):  # (T, F) products only: no (T, n, F, F) intermediate
            gram[i] += flat.T @ (flat * w[..., i].reshape(-1, 1))
        cross += torch.einsum("btf,btn->nf", th, w * r)
        misfit += (w * r**2).sum(dim=(0, 1))
    restored = []
    for i in range(n_states):
        if not bool(free_rows[i]):
            continue
        while True:
            active = torch.nonzero(model.support[i]).flatten().tolist()
            base = _explained(gram[i], cross[i], active)[0]
            left = float(misfit[i]) - base
            best = None
            for j in torch.nonzero(~model.support[i]).flatten().tolist():
                gain, coef = _explained(gram[i], cross[i], active + [j])
                gain -= base
                if abs(float(coef[-1])) >= threshold and gain >= min_gain * left and (
                        best is None or gain > best[0]):
                    best = (gain, j, coef)
            if best is None:
                break
            _, j, coef = best
            model.restore_constant(i, j)
            model.constants[i, active + [j]] += coef.to(model.constants.dtype)
            misfit[i] -= best[0] + base  # the corrections are now part of the model
            cross[i] -= gram[i][:, active + [j]] @ coef
            restored.append((i, j))
    return restored


def between_phases(model, theta, xdot, weights, inputs, threshold, free_rows, decide=None):
    """The checks both generators run between support and refit: pruned terms the data
    still need (:func:`restore_terms`) and terms absorbed into a varying coefficient
    (:func:`restore_absorbed_terms`) come back, recorded in ``model.restored``; then
    ``decide(model)``, if given (the exact model's structure)."""
    model.restored = restore_terms(model, theta, xdot, weights, inputs, threshold, free_rows)
    model.restored += restore_absorbed_terms(model, theta, xdot, weights, inputs, threshold,
                                             free_rows)
    if decide is not None:
        decide(model)


def _explained(gram, cross, cols):
    """Weighted sum of squares explained by a least-squares fit on ``cols``, and the fit."""
    if not cols:
        return 0.0, gram.new_zeros(0)
    g = gram[cols][:, cols]
    g = g + 1e-10 * torch.trace(g) * torch.eye(len(cols), dtype=g.dtype, device=g.device)
    coef = torch.linalg.solve(g, cross[cols])
    return float(cross[cols] @ coef), coef


PIN_PRECISION = 10.0  # pin a constant the exact model knows to 10% (|value| / sd)


@torch.no_grad()
def adopt_structure(model, choices) -> list[tuple[int, int]]:
    """Set each equation's support and varying terms to the exact model's choice
    (:class:`~.structure.EquationChoice` per equation, None: leave it) and pin the
    constant terms that it determines to 10% at its estimates (normalised units); the
    others are left to the generator (a freely varying term can make constants
    unidentified, and the exact model's value is then its prior's). Returns the
    (equation, term) pairs added to the support."""
    added = []
    n_features = model.support.shape[1]
    for i, choice in enumerate(choices):
        if choice is None:
            continue
        fit = choice.fit
        support, varying = set(fit.support), set(fit.varying)
        for j in range(n_features):
            if j in support and not bool(model.support[i, j]):
                model.restore_constant(i, j)
                added.append((i, j))
            elif j not in support:
                model.support[i, j] = False
        for j in varying:
            if not float(model.time_varying[i, j]):
                model.free_variation(i, j)
        for j, value, sd in zip(fit.constant, fit.constants, fit.constant_sd(), strict=True):
            if abs(float(value)) >= PIN_PRECISION * float(sd):
                model.pin_constant(i, j, float(value))
            else:
                model.time_varying[i, j] = 0.0
    return added
