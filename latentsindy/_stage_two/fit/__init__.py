"""Closed systems fitted to the observed series by integrating them: the parametric
system (``field``), multiple shooting (``shooting``), Levenberg-Marquardt
(``least_squares``), the refinement and its held-out score (``refine``) and term
selection on the integrated fit (``terms``)."""
