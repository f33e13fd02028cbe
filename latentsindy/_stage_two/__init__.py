"""Stage two (ours): time-varying coefficients become hidden states of a closed,
autonomous ODE, chosen among hypotheses by integrating each against the data.

Grouped by what each part does, in the order :func:`discover_hidden` runs them:

* ``discover``: the entry point; runs stage one (``latentsindy._stage_one``) on the
  longest segment (and those at least half as long), picks the coefficients that vary
  and builds the shared :class:`~.context.Context`;
* ``context``: the data as stage two sees them, and the thresholds more than one part
  reads (a threshold read in one module only is defined there);
* ``propose/``: structures that could explain the data (stage one's, each term as the
  carrier, shared variation, nested states), each with its hidden series (``smoother``)
  and a cheap closure (``closure``), ranked by the closure's held-out error;
* ``fit/``: closed systems fitted by integrating them (``field``: the parametric system;
  ``shooting``: multiple shooting; ``least_squares``: Levenberg-Marquardt; ``refine``:
  the fit and its held-out score; ``terms``: term selection on the integrated fit);
* ``verdict`` and ``judge``: each proposal fitted, its terms selected, scored on
  held-out segments; ``ranking`` picks the sparsest system the held-out data do not
  reject against the best, and lists those it cannot tell from it; ``restate`` tries
  the winner written another way (``rewrite/``: a hidden state shifted by observed
  functions, ``gauge``; a state and its rate as one state with a first integral,
  ``first_integral``; a state that is a function of the observed ones,
  ``observed_function``);
* ``doubts/``: the checks on the chosen system, each failed one a
  :class:`~latentsindy.results.Doubt` (score and convergence, terms, states, the
  whole-recording run, terms beyond the search, a nested state folded back);
* ``assemble``: the winner, its alternatives and its doubts become the result
  (``result``, ``result_parts``, ``summary``, ``figures``).

Dependencies point one way: ``context`` <- ``fit`` <- ``rewrite`` <- ``propose`` <-
``verdict`` <- ``ranking`` <- ``judge``/``restate`` <- ``doubts`` <- ``assemble`` <- ``discover``.
"""
