"""Labels: importers from other tools, triangulation, checks, merge/split/export (the
training-set reader is :mod:`freipose.nn.dataset`)."""
