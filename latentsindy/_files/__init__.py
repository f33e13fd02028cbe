"""Files: what latentsindy writes and reads. Formats depend on the result types, never
the reverse (results call ``_core.saving.save``; each format registers its writer).

* ``container``: the ``.npz`` of plain arrays plus one JSON document that every file uses;
* ``expressions``: equations as trees of whitelisted node types, never as code;
* ``result_file``: a :class:`HiddenDiscovery`; ``model_file``: a fitted :class:`DynamicSINDy`;
* ``load``: :func:`latentsindy.load`, which reads either;
* ``tables``: named numeric columns from CSV, NPZ and HDF5 data (for the command line).
"""
