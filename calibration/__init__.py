"""Multi-camera calibration from board videos (installed as ``freipose.calibration``)."""
