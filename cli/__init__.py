"""The ``freipose`` command line (installed as ``freipose.cli``)."""
