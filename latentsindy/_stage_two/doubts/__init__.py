"""The checks on the chosen system; each failed check is a
:class:`~latentsindy.results.Doubt` saying what failed and what to try.

* ``checks``: held-out score, convergence, significance, constants per recording;
* ``terms``: terms exchangeable, weakly supported, nearly needed, beyond the search;
* ``states``: a state that is a function of others, written twice, faster than the
  sampling, or with a first integral not preferred;
* ``runs``: the closed system over whole recordings, with a finite budget;
* ``beyond``: terms outside every candidate that the data call for;
* ``folded``: a nested hidden state folded back into a law one degree higher.
"""
