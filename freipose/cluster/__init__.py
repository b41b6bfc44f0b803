"""Long jobs as units on an executor: worker processes here, or a SLURM cluster.

``freipose predict --executor local|slurm`` cuts every session into chunks of frames
(:mod:`freipose.cluster.predict`), runs them through an engine (:mod:`.executors`: a process
pool, or SLURM job arrays submitted with submitit), resubmits the ones that fail
(:mod:`.driver`) and joins each session when its chunks are complete. ``freipose jobs``
shows the units (:mod:`.status`).
"""
