"""Installed as ``freipose.cli`` (the top-level ``cli/``, see package-dir): the command line."""
