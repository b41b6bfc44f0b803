"""FreiPose: markerless multi-camera 3D motion capture of lab animals.

See ``freipose.geometry`` for the conventions (units, axes, camera model) that every
module follows, and ``docs/formats.md`` for the file formats.
"""

__version__ = "0.1.0"

__all__ = ["__version__"]
