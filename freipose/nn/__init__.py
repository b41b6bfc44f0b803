"""The FreiPose pose network (PyTorch): voxel network, triangulation baseline, training.

Public API:

* :mod:`freipose.nn.config`: :class:`TrainConfig`, :class:`ModelConfig`, presets
  ``tiny``/``small``/``paper``, :func:`load_config`;
* :mod:`freipose.nn.types`: the typed dicts that flow through the network
  (:class:`Sample`, :class:`PreparedSample`, :class:`Batch`, :class:`NetworkOutput`,
  :class:`Prediction`);
* :mod:`freipose.nn.dataset`: :class:`MultiViewDataset` (samples from ``labels.h5``);
* :mod:`freipose.nn.data`: :func:`prepare_sample` (crops + crop cameras of a sample),
  :func:`collate_prepared`;
* :mod:`freipose.nn.model`: :class:`VoxelPoseNet`, :class:`BaselineNet`, :func:`build_model`;
* :mod:`freipose.nn.checkpoint`: :func:`load_checkpoint`, :func:`read_checkpoint`;
* :mod:`freipose.nn.inference`: :func:`predict_batch`, :func:`predict_prepared`,
  :func:`triangulate_baseline`;
* :mod:`freipose.nn.train`: :func:`train_pose`, :func:`train_from_config`;
* :mod:`freipose.nn.evaluate`: :func:`predict_dataset`, :func:`jpe`, :func:`write_report`.

Nothing is imported here so that ``import freipose.nn`` stays cheap.
"""
