"""Long jobs as units on an executor: worker processes here, or a SLURM cluster.

A command run with ``--executor local|slurm`` describes its work as a stage task
(:mod:`freipose.cluster.stages`): ``predict`` and ``detect`` cut every session into chunks
of frames (:mod:`.predict`, :mod:`.detect`); ``smooth``, ``analyze variables`` and
``render`` make one unit per output (:mod:`.smooth`, :mod:`.variables`, :mod:`.render`).
The units run through an engine (:mod:`.executors`: a process pool, or SLURM job arrays
submitted with submitit); the driver (:mod:`.driver`) resubmits the ones that fail, and
each output is joined when its units are complete. ``freipose jobs`` shows the units
(:mod:`.status`); ``freipose train --executor`` runs one training job (:mod:`.train`).
"""
