"""Stage two (ours): time-varying coefficients become hidden states of a closed,
autonomous ODE, chosen among hypotheses by integrating each against the data.

The modules, in the order :func:`discover_hidden` runs them:

1. ``discover``: the entry point; runs stage one (``latentsindy._stage_one``) on the
   longest segment (and those at least half as long), picks the coefficients that vary
   and builds the shared ``Context``;
2. ``hypotheses``: structures that could explain the data (stage one's, each term as
   the carrier, shared variation); each gets its hidden series from ``smoother`` and a
   cheap closure from ``closure`` (sparse regression), which ranks them;
3. ``judge``: each proposal's closed system (``field``) is refined by integration
   (``refine`` on ``shooting``: multiple shooting, Levenberg-Marquardt), its terms
   selected on the integrated likelihood (``terms``), then scored on held-out segments;
   ``rank`` picks the sparsest system within one standard error of the best, which is
   also tried restated: a hidden state and its rate as one hidden state where the
   rate's law has a first integral (``first_integral``), or its hidden states shifted
   by observed functions (``gauge``);
4. ``assemble``: the winner, its alternatives and its doubts (``checks``; terms beyond
   the search, ``beyond``; a nested state folded back into a law one degree higher,
   ``folded``) become the result, ``result.HiddenDiscovery`` (with ``figures`` for its
   plot).
"""
