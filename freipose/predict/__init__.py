"""Prediction on recordings: sessions of synchronized videos -> ``poses.h5``.

* ``session``: find and validate sessions (videos + calibration) before any work.
* ``reader``: background decoding of all camera streams, batched and synchronized.
* ``estimator``: the :class:`~freipose.predict.estimator.PoseEstimator` interface.
* ``network``: the real estimator (detector + voxel network).
* ``writer``: incremental, resumable ``poses.h5`` writer.
* ``run``: the prediction loop, sharding (``--shard I/N``).
* ``merge``: join shard files.
* ``export``: CSV, Anipose CSV, DLC-3D CSV, NWB (ndx-pose).
* ``render``: overlay videos.
* ``select``: frames to label next.
"""
