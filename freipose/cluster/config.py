"""Where FreiPose's long jobs run: the ``[cluster]`` table and the executor options.

A cluster file is a small TOML file with one ``[cluster]`` table::

    [cluster]
    executor = "slurm"        # or "local"
    partition = "gpu"
    account = "mylab"
    gpus = 1                  # GPUs per unit
    cpus = 4                  # CPU cores per unit (the unit's PyTorch threads)
    mem_gb = 16
    time_min = 120            # time limit of one unit
    array_parallelism = 32    # units running at once
    chunk_frames = 6000       # frames per unit (a session of 180 000 frames: 30 units)
    max_retries = 2           # a unit that fails is resubmitted at most this often

Every key is optional; the command line's ``--executor`` and ``--cluster-*`` options
override the file's values.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from freipose.errors import FreiPoseError
from freipose.io.toml import dataclass_from_table, read_toml

EXECUTORS = ("local", "slurm")


class ClusterConfigError(FreiPoseError):
    """A ``[cluster]`` value is missing, unknown or out of range; the message names it."""


@dataclass(frozen=True)
class ClusterConfig:
    """How the units of a long job are run.

    Attributes:
        executor: ``"local"`` (worker processes on this machine) or ``"slurm"``.
        partition: SLURM partition (empty: the cluster's default).
        account: SLURM account to charge (empty: the user's default).
        qos: SLURM quality of service (empty: default).
        gpus: GPUs per unit (0: CPU only).
        cpus: CPU cores per unit; each unit runs that many PyTorch threads.
        mem_gb: memory per unit in GB.
        time_min: time limit of one unit in minutes.
        array_parallelism: most units running at once (SLURM array throttle; the local
            executor's number of worker processes).
        chunk_frames: frames per unit; rounded up to whole batches.
        max_retries: how often a failed, cancelled or timed-out unit is resubmitted
            before it is reported as failed.
        poll_s: seconds between two looks at the scheduler.
        sbatch: further ``#SBATCH`` options (name -> value, e.g. ``constraint = "a100"``).
    """

    executor: str = "local"
    partition: str = ""
    account: str = ""
    qos: str = ""
    gpus: int = 0
    cpus: int = 1
    mem_gb: float = 8.0
    time_min: int = 120
    array_parallelism: int = 16
    chunk_frames: int = 6000
    max_retries: int = 2
    poll_s: float = 10.0
    sbatch: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.executor not in EXECUTORS:
            raise ClusterConfigError(
                f"[cluster] executor must be one of {', '.join(EXECUTORS)}, got {self.executor!r}"
            )
        minimum = {"gpus": 0, "cpus": 1, "time_min": 1, "array_parallelism": 1,
                   "chunk_frames": 1, "max_retries": 0}  # fmt: skip
        for key, low in minimum.items():
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ClusterConfigError(
                    f"[cluster] {key} must be a whole number >= {low}, got {value!r}"
                )
        for key in ("mem_gb", "poll_s"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ClusterConfigError(f"[cluster] {key} must be a number, got {value!r}")
            if not math.isfinite(value) or value <= 0:
                raise ClusterConfigError(f"[cluster] {key} must be > 0, got {value!r}")
        if not isinstance(self.sbatch, Mapping):
            raise ClusterConfigError("[cluster] sbatch must be a table of #SBATCH options")

    def replace(self, **changes: Any) -> ClusterConfig:
        """A copy with ``changes`` (None values are ignored: options left unset)."""
        return dataclasses.replace(self, **{k: v for k, v in changes.items() if v is not None})


def read_cluster_config(path: str | Path | None, **overrides: Any) -> ClusterConfig:
    """The ``[cluster]`` table of ``path`` (None: defaults) with ``overrides`` applied.

    Raises:
        ClusterConfigError: an unknown key or a bad value.
        TomlFileError: the file cannot be read or parsed.
    """
    table: dict[str, Any] = {}
    if path is not None:
        doc = read_toml(path)
        if "cluster" not in doc:
            raise ClusterConfigError(
                f"{path}: no [cluster] table; write the executor's settings under [cluster] "
                "(see the documentation's page Run a study on a cluster)"
            )
        table = dict(doc["cluster"])
    config = dataclass_from_table(ClusterConfig, table, f"{path} [cluster]", ClusterConfigError)
    return config.replace(**overrides)
