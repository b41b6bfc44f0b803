"""``freipose demo``: the whole FreiPose workflow on synthetic recordings, with a report.

Steps (each calls the same library code as the corresponding ``freipose`` command; one
module per step in :mod:`freipose.demo.steps`):

1. ``synth``     render a calibration recording (a ChArUco board waved through the arena)
                 and stimulated sessions of a rat filmed by 7 cameras (``freipose synth``);
2. ``calibrate`` calibrate the cameras from the board videos (``freipose calib``) and compare
                 with the true rig (camera centre, rotation and focal length errors);
3. ``labels``    import labels of a few hundred time instants: 2D labels of the visible
                 keypoints (with 1 px labelling noise) triangulated with the calibrated rig
                 (what ``freipose labels`` produces from a 2D labelling tool);
4. ``train``     train the box detector, the voxel network and the triangulation baseline
                 (``freipose train --stage detector|pose|baseline``);
5. ``predict``   predict every session to ``poses/<session>.poses.h5`` (``freipose predict``)
                 and render an overlay clip (``freipose render``);
6. ``evaluate``  joint position errors against the true 3D keypoints, voxel network vs.
                 triangulation baseline (``freipose eval``) and of the whole pipeline;
7. ``analyze``   behavioural variables and attribution of the stimulation effect
                 (``freipose analyze``);
8. ``report``    ``OUTDIR/report.html`` with every step's figures (:mod:`freipose.demo.report`).

The sizes of a run are a preset (:mod:`freipose.demo.presets`); the runner
(:func:`freipose.demo.runner.run_demo`) skips finished steps (:mod:`freipose.demo.markers`).
"""
