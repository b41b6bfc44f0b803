"""The browser labeling tool of ``freipose label``: server, API and the page it serves."""
