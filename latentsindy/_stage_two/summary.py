"""A discovery's summary as text (:meth:`HiddenDiscovery.summary`)."""

from __future__ import annotations

import numpy as np
import sympy as sp


def summary_text(result) -> str:
    """The closed system, its coefficients with standard errors, how it was fitted
    and judged, doubts, equally good alternatives (or the runner-up) and notes."""
    lines = [f"Closed system: {len(result.observed_names)} observed + "
             f"{len(result.hidden_names)} hidden state(s)"]
    lines += [f"  hidden: {h.describe()}" for h in result.hidden_states]
    rhs = result.rhs
    lines += [f"  d{n}/dt = {_short(rhs[n])}" for n in result.state_names]
    estimated = [t for t in result.terms if t.state in result.hidden_names and not t.fixed
                 and np.isfinite(t.stderr)]
    if estimated:
        lines.append("  hidden-equation coefficients (value +- standard error):")
        lines += [f"    d{t.state}/dt: {t.feature}: {t.value:.6g} +- {t.stderr:.2g}"
                  for t in estimated]
    if result.refinement is not None:
        r = result.refinement
        lines.append(f"  refined by integration: misfit {r.misfit_before:.4g} -> "
                     f"{r.misfit_after:.4g} (RMS / std of the data), {r.n_segments} "
                     f"segments, {r.status}")
    if np.isfinite(result.score):
        lines.append(f"  held-out score {result.score:.4g} +- {result.score_se:.2g} "
                     "(noise variances; ~1: reproduces unseen data down to its noise)")
    lines += [f"  DOUBT: {d}" for d in result.doubts]
    if result.uncertain:
        lines.append("  STRUCTURE UNCERTAIN: these systems explain the data as well (other "
                     "hidden states, no larger; favoured on held-out data; or stage one's "
                     "own law, towards which the held-out data lean; the simplest is shown "
                     "above):")
        for alt in result.uncertain:
            lines.append(f"    - {alt.description}: score {alt.score:.4g} +- "
                         f"{alt.score_se:.2g}, {alt.size} parameters")
            lines += [f"        d{n}/dt = {_short(e)}" for n, e in alt.rhs.items()]
    elif result.alternatives:
        alt = result.alternatives[0]
        what = "score" if alt.status == "scored" else "in-sample misfit"
        value = f"{what} {alt.score:.4g} " if np.isfinite(alt.score) else ""
        lines.append(f"  runner-up: {alt.description}, {value}({alt.status}), "
                     f"{alt.size} parameters")
    if result.data_use is not None:
        lines.append(f"  data: {result.data_use.sentence()}")
    lines += [f"  note: {n}" for n in result.notes]
    return "\n".join(lines)

def _short(expr):
    return str(expr.xreplace({f: sp.Float(float(f), 5) for f in expr.atoms(sp.Float)}))
