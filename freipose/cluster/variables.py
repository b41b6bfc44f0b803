"""``freipose analyze variables --executor ...``: the poses file as one unit.

The variables' filters, gap interpolation and STFTs run over the whole recording, so the
file is not cut in time: the unit writes ``VARS.h5`` as a single run does.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from freipose.cluster.driver import Unit
from freipose.cluster.stages import FileJob, WholeOutputs, poses_frames


@dataclass(frozen=True)
class VariablesTask(FileJob, WholeOutputs):
    """Everything the unit of one ``analyze variables`` needs (pickled into its job).

    Attributes:
        poses: the poses file.
        out_path: the ``VARS.h5`` to write.
        skeleton: the skeleton's name or TOML (None: the poses' own).
        floor: ``world``, ``auto`` or a floor TOML.
        config: the ``VariableConfig``.
        frames: the poses' frames.
        threads: OpenCV threads of the unit.
    """

    command: ClassVar[str] = "analyze variables"
    noun: ClassVar[str] = "file"
    uses_torch: ClassVar[bool] = False

    poses: Path
    out_path: Path
    skeleton: str | None
    floor: str
    config: Any
    frames: int = 0
    threads: int = 1

    @classmethod
    def of(cls, poses: Path, out_path: Path, **kwargs: Any) -> VariablesTask:
        """The task of ``poses`` (its frames read here)."""
        return cls(poses, out_path, frames=poses_frames(poses), **kwargs)

    def outputs(self) -> dict[str, tuple[Path, int]]:
        """The poses file's name -> (``VARS.h5``, its frames)."""
        return {self.poses.name.removesuffix(".h5"): (self.out_path, self.frames)}

    def run_unit(self, unit: Unit, on_first: Callable[[], None]) -> None:
        """Compute and write the variables (under the output's lock)."""
        from freipose.analysis.io import (
            variables_from_poses,
            variables_settings,
            write_variables_h5,
        )
        from freipose.io.lock import output_lock
        from freipose.io.poses import read_poses_h5

        data = read_poses_h5(self.poses, require_up=True)
        on_first()
        var = variables_from_poses(data, self.skeleton, self.floor, self.config,
                                   source=str(self.poses))  # fmt: skip
        settings = variables_settings(self.skeleton, self.floor, self.config)
        with output_lock(self.out_path, "variables file"):
            write_variables_h5(var, self.out_path, settings, source=self.poses)
