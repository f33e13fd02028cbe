"""A doubt: one check that a result failed, as a kind and a sentence.

A :class:`Doubt` is a ``str`` (its message), so it prints, compares and searches like
the sentence it is; its :attr:`~Doubt.kind` names the check, so code can act on kinds
without matching text.
"""

from __future__ import annotations

# The kinds, each with what failed. A new check adds its kind here (and to the docs).
KINDS = {
    # stage two: the closed system
    "not checked": "the system was not refined by integration, so nothing was checked",
    "not scored": "the system could not be scored on held-out data",
    "score": "the system does not reproduce held-out data down to their noise",
    "not converged": "refinement by integration did not converge",
    "not continuous": "the fitted integration segments do not meet: no trajectory of the "
                      "system, and its terms were not checked",
    "insignificant": "a hidden-equation coefficient is within two standard errors of zero",
    "recording constant": "a constant differs between recordings",
    "exchangeable term": "a term can be exchanged for another with almost no loss of fit",
    "weak term": "a term is supported only weakly by the data",
    "missing term": "a term left out is nearly called for by the data",
    "beyond library": "the data call for terms no candidate system held",
    "folded law": "a law of one degree higher without the nested state fits as well",
    "first integral": "a first integral of the hidden law was not preferred",
    "observed function": "a hidden state is a function of the observed states",
    "partial shift": "a hidden state shifted by part of an observed term gives the same "
                     "dynamics with fewer terms",
    "redundant state": "two hidden states are one state written twice",
    "unresolved": "a hidden state moves faster than the sampling resolves",
    "free run": "the system integrated over a whole recording blows up or runs out of budget",
    "no law": "no term of the library was kept: no law was found",
    "without stage one": "found without stage one (too few samples per cycle, or short "
                         "recordings), the law keeps every closure term: no sparse law",
    "weak check": "the held-out check has little power on these data (a right system "
                  "would score well above the noise there)",
    "time budget": "max_time was spent before the judgement ended: some hypotheses or "
                   "steps were not judged",
    # stage one: the coefficients' structure
    "rival structure": "another structure explains the derivatives about as well",
    "two optima": "the structure search has two optima",
    "preferred structure": "the exact model prefers another structure",
    "equation misfit": "a fitted equation misses the derivatives by more than their noise",
    "generator misfit": "the generator misses the derivatives by more than their noise",
    "small term": "a term explains so little that a small change of threshold drops it",
    "generator disagreement": "the generator's and the exact model's variation disagree",
    # files written before doubts had kinds
    "unspecified": "a doubt read from a file written before doubts had kinds",
}


class Doubt(str):
    """A failed check: its message (the ``str`` itself) and its kind.

    Parameters
    ----------
    kind : str
        One of :data:`KINDS` (``Doubt.kinds()`` lists them).
    message : str
        What failed and what it means, as one sentence.

    Examples
    --------
    >>> d = Doubt("weak term", "dh/dt: the term x is supported only weakly")
    >>> d.kind, "weak" in d
    ('weak term', True)
    >>> print(d)
    dh/dt: the term x is supported only weakly
    """

    kind: str

    def __new__(cls, kind: str, message: str) -> Doubt:
        if kind not in KINDS:
            raise ValueError(f"kind must be one of {sorted(KINDS)}; got {kind!r}.")
        if not isinstance(message, str):
            raise TypeError(f"message must be a str; got {type(message).__name__}.")
        self = super().__new__(cls, message)
        self.kind = kind
        return self

    @property
    def message(self) -> str:
        """The sentence, as a plain ``str``."""
        return str.__str__(self)

    def __repr__(self) -> str:
        return f"Doubt({self.kind!r}, {self.message!r})"

    def __reduce__(self):
        return (Doubt, (self.kind, self.message))

    @staticmethod
    def kinds() -> dict[str, str]:
        """Every kind and what it means."""
        return dict(KINDS)


def as_doubts(values, kind: str = "unspecified") -> tuple[Doubt, ...]:
    """Doubts from ``values``: a :class:`Doubt` is kept, a plain ``str`` gets ``kind``."""
    return tuple(v if isinstance(v, Doubt) else Doubt(kind, str(v)) for v in values)


def read_doubts(messages, kinds=None) -> tuple[Doubt, ...]:
    """Doubts read back from a file: ``kinds`` beside the messages, or none (files
    written before doubts had kinds: each is ``"unspecified"``)."""
    messages = [str(m) for m in messages]
    kinds = ["unspecified"] * len(messages) if kinds is None else [str(k) for k in kinds]
    if len(kinds) != len(messages):
        raise ValueError(f"a file lists {len(messages)} doubts but {len(kinds)} kinds; it "
                         "was not written by latentsindy or is damaged.")
    return tuple(Doubt(k if k in KINDS else "unspecified", m)
                 for k, m in zip(kinds, messages, strict=True))
