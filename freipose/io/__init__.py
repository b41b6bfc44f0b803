"""File formats: every reader and writer of FreiPose (documented in ``docs/formats.md``)."""
