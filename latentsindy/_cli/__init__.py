"""Running discovery from outside Python and on many recordings at once.

* ``batch``: :func:`discover_many`, recordings and seeds in parallel through joblib,
  one :class:`Run` (and one table row) each;
* ``main``: the ``latentsindy`` command line (discover, show, simulate); its folder
  mode runs ``batch``.
"""
