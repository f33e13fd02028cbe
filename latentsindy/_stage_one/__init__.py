"""Stage one (the seed paper's dynamic SINDy): the observed series x(t) to time-varying
SINDy coefficients Xi(t) with Theta(x) Xi(t) ~ xdot, and their uncertainty.

The modules, in the order a fit runs them:

1. ``estimator``: :class:`DynamicSINDy` validates the input, differentiates it
   (``_core.derivatives``), normalises derivatives and library columns, builds the
   generator (``latentsindy.generators``: timeVAE or dynamic HyperSINDy) and the exact
   model (``evidence``), and trains;
2. ``training`` (timeVAE) or ``sequential`` with ``sequential_model`` and
   ``sequential_options`` (HyperSINDy, window by window): the two phases, support
   (pruning) then refit, of ``coefficient_model`` (Xi(t) from the generator).
   timeVAE's loss is defined once, in ``loss`` (its terms, weights and assembly; torch's
   autograd evaluates it on a GPU); on a CPU ``numpy_step`` writes the step out, its
   layers by the compiled ``step_kernels``, its loss by ``numpy_loss`` on the samples
   or ``knot_loss`` on the decoder's knots (the same loss, re-expressed);
   ``flat_adam`` is timeVAE's optimiser (torch's Adam and gradient clipping on one
   flat buffer, compiled on a CPU);
3. ``decisions``, between the phases: freezing variation that does not pay, restoring
   pruned terms the data still need, then adopting the exact model's structure;
4. ``evidence``: the exact varying-coefficient model of the data (``vcm``: B-splines in
   time and the integral form's normal equations; ``vcm_fit``: evidence and posterior
   of one equation's structure; ``structure``: the search over support and varying
   terms);
5. ``assessment``, after the refit: the exact model's posterior, which makes the band,
   and the doubts;
6. ``coefficients``: the result, :class:`CoefficientSeries`, and ``figures`` its plot.

Stage two (``latentsindy._stage_two``) starts from a fitted :class:`DynamicSINDy`.
"""
