"""Labels: importers from other tools, triangulation, checks, merge/split/export and the
training-set reader (:mod:`freipose.labels.dataset`)."""
