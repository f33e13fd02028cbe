"""Hidden states shared by several varying coefficients: the structures
:func:`.hypotheses.propose` builds from stage one's variation factored by rank, from
the best carrier of every varying equation, and from every pair of carriers of two
equations."""

from __future__ import annotations

import itertools

import numpy as np

from .smoother import Structure


def shared_variation(support, pairs, series, max_rank):
    """Stage one's varying terms with their variation factored at ranks 1..``max_rank``:
    pivots chosen greedily (the most significant term, then the one least explained by
    the pivots so far), other terms' loadings by least squares on the pivots."""
    if not pairs:
        return []
    n_obs, n_feat = support.shape
    z = np.asarray(series, float)
    z = (z - z.mean(axis=0)) / np.maximum(z.std(axis=0), 1e-300)
    out = []
    pivots = [0]
    for rank in range(1, min(len(pairs), max_rank) + 1):
        if rank > 1:
            basis = np.column_stack([np.ones(len(z)), z[:, pivots]])
            resid = z - basis @ np.linalg.lstsq(basis, z, rcond=None)[0]
            left = np.sum(resid**2, axis=0)
            left[pivots] = -1
            pivots.append(int(np.argmax(left)))
        loads = np.zeros((n_obs, n_feat, rank))
        raw = np.asarray(series, float)
        basis = np.column_stack([np.ones(len(raw)), raw[:, pivots]])
        fit = np.linalg.lstsq(basis, raw, rcond=None)[0][1:]  # (rank, n_terms)
        for col, (i, k) in enumerate(pairs):
            loads[i, k] = fit[:, col]
        for a, col in enumerate(pivots):
            i, k = pairs[col]
            loads[i, k] = 0.0
            loads[i, k, a] = 1.0
        sup = support.copy()
        for i, k in pairs:
            sup[i, k] = True
        out.append(Structure(sup, loads, tuple(pairs[c] for c in pivots)))
    return out


def carrier_pairs(every, support):
    """One hidden state shared by a carrier of one equation and a carrier of another,
    for every pair of equations and carriers (the loading of the second from the
    affine relation of the two carriers' own series, refined by the smoother).

    The best-closing carrier of each equation alone need not be the shared one: Lorenz
    seen through x and z carries y as the coefficient of 1 in dx/dt and of x in dz/dt,
    but with the other equation unexplained, z in dx/dt (sigma y / z) and x^2 in dz/dt
    (y / x) closed better, and together they are no one hidden state."""
    n_obs, n_feat = support.shape
    usable = {i: [(p, s) for p in ps if (s := _series(p)) is not None]
              for i, ps in every.items()}
    out = []
    for i, j in itertools.combinations(sorted(usable), 2):
        for p, a in usable[i]:
            for q, b in usable[j]:
                (pi, pk), = p.structure.pivots
                (qi, qk), = q.structure.pivots
                loads = np.zeros((n_obs, n_feat, 1))
                loads[pi, pk, 0] = 1.0
                loads[qi, qk, 0] = np.polyfit(a, b, 1)[0]
                sup = support | p.structure.support | q.structure.support
                out.append(Structure(sup, loads, ((pi, pk),)))
    return out


def _series(p):
    """A single-carrier proposal's hidden series, concatenated; None if not finite or
    constant."""
    if not (np.isfinite(p.score) and np.isfinite(p.fit.misfit)):
        return None
    h = np.concatenate([h[:, 0] for h in p.fit.hidden])
    return h if np.all(np.isfinite(h)) and np.std(h) > 0 else None


def across_equations(best, support):
    """One hidden state shared by the best carrier of every varying equation (loadings
    from the affine relation of their series), and one hidden state per equation."""
    items = sorted(best.items(), key=lambda kv: kv[1].score)
    n_obs, n_feat = support.shape
    sup = support.copy()
    for _, p in items:
        sup |= p.structure.support
    h0 = np.concatenate([h[:, 0] for h in items[0][1].fit.hidden])
    shared = np.zeros((n_obs, n_feat, 1))
    separate = np.zeros((n_obs, n_feat, len(items)))
    pivots = []
    for a, (_, p) in enumerate(items):
        (pi, pk), = p.structure.pivots
        hs = np.concatenate([h[:, 0] for h in p.fit.hidden])
        slope = np.polyfit(h0, hs, 1)[0] if a else 1.0
        shared[pi, pk, 0] = slope
        separate[pi, pk, a] = 1.0
        pivots.append((pi, pk))
    return [Structure(sup, shared, (pivots[0],)), Structure(sup, separate, tuple(pivots))]
