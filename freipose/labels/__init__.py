"""Labels: importers from other tools, triangulation, checks, merge/split/export.

The training-set reader is :mod:`freipose.nn.dataset`.
"""
