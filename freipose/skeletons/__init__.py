"""The skeletons shipped with FreiPose (``rat``, ``mouse``, ``paw``) as TOML files."""
