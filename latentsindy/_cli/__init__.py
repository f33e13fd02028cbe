"""The ``latentsindy`` command line (discover, show, simulate); its folder mode runs
:func:`latentsindy.discover_many` (``latentsindy._batch``)."""
