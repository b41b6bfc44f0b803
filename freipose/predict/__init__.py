"""Prediction on recordings: sessions of synchronized videos -> ``poses.h5``.

* ``reader``: background decoding of all camera streams, batched and synchronized.
* ``estimator``: the :class:`~freipose.predict.estimator.PoseEstimator` interface.
* ``network``: the real estimator (detector + voxel network).
* ``writer``: incremental, resumable ``poses.h5`` writer.
* ``run``: the prediction loop, sharding (``--shard I/N``).
* ``merge``: join shard files.
* ``render``: overlay videos.

Sessions (videos + calibration, validated before any work) are
:mod:`freipose.io.session`; the export formats (CSV, Anipose CSV, DLC-3D CSV, NWB) are
:mod:`freipose.io.export`; frames to label next are :mod:`freipose.labels.select`.
"""
