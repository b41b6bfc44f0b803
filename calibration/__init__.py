"""Installed as ``freipose.calibration``: the top-level ``calibration/`` (pyproject's package-dir).

Multi-camera calibration from board videos: boards (:mod:`~freipose.calibration.boards`, their
files in :mod:`~freipose.calibration.board_files`), their detection in images
(:mod:`~freipose.calibration.detect`) and videos (:mod:`~freipose.calibration.detect_videos`,
with :mod:`~freipose.calibration.tracking` and :mod:`~freipose.calibration.detection_cache`;
:mod:`~freipose.calibration.diagnose` explains a board that is never found), the solver
(:mod:`~freipose.calibration.intrinsics`, :mod:`~freipose.calibration.extrinsics`,
:mod:`~freipose.calibration.bundle`), the pipeline that runs it as named stages
(:mod:`~freipose.calibration.pipeline` with :mod:`~freipose.calibration.options`,
:mod:`~freipose.calibration.stages`, :mod:`~freipose.calibration.model_selection`,
:mod:`~freipose.calibration.world` and :mod:`~freipose.calibration.stats`) and its report
(:mod:`~freipose.calibration.report`).
"""
