"""The FreiPose pose network (PyTorch): voxel network, triangulation baseline, training.

Public API:

* :mod:`freipose.nn.config`: :class:`TrainConfig`, :class:`ModelConfig`, presets
  ``tiny``/``small``/``paper``, :func:`load_config`;
* :mod:`freipose.nn.model`: :class:`VoxelPoseNet`, :class:`BaselineNet`,
  :func:`load_checkpoint`, :func:`predict_batch`, :func:`triangulate_baseline`;
* :mod:`freipose.nn.data`: :func:`prepare_sample` (crops + crop cameras from a
  ``MultiViewDataset`` sample), :func:`collate_prepared`;
* :mod:`freipose.nn.train`: :func:`train_pose`, :func:`train_from_config`;
* :mod:`freipose.nn.evaluate`: :func:`predict_dataset`, :func:`jpe`, :func:`write_report`.

Nothing is imported here so that ``import freipose.nn`` stays cheap.
"""
