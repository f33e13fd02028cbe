"""Stage one (the seed paper's dynamic SINDy): the observed series x(t) to time-varying
SINDy coefficients Xi(t) with Theta(x) Xi(t) ~ xdot, and their uncertainty.

The modules, in the order a fit runs them:

1. ``estimator``: :class:`DynamicSINDy` validates the input, differentiates it
   (``_core.derivatives``), normalises derivatives and library columns, builds the
   generator (``latentsindy.generators``: timeVAE or dynamic HyperSINDy) and trains;
2. ``training`` (timeVAE) or ``sequential`` with ``sequential_model`` and
   ``sequential_options`` (HyperSINDy, window by window): the loss and the two phases,
   support (pruning) then refit;
3. ``decisions``, between the phases: freezing variation that does not pay, restoring
   pruned terms the data still need;
4. ``coefficients``: the result, :class:`CoefficientSeries`, and ``figures`` its plot.

Stage two (``latentsindy._stage_two``) starts from a fitted :class:`DynamicSINDy`.
"""
