"""``freipose smooth --executor ...``: one unit per poses file.

The smoother runs forward and backward over a whole recording, so a file is not cut in
time (its chunks would be smoothed differently from the whole); every file is one unit
that writes ``OUTDIR/<name>.poses.h5`` as :func:`freipose.predict.smooth.smooth_file` does
in a single run.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from freipose.cluster.driver import Unit
from freipose.cluster.stages import FolderJob, WholeOutputs, poses_frames


@dataclass(frozen=True)
class SmoothTask(FolderJob, WholeOutputs):
    """Everything every unit of one smoothing needs (pickled into each job).

    Attributes:
        files: (poses file, smoothed file it becomes, its frames) per input.
        outdir: the folder of the smoothed files.
        error_floor: the network's held-out error (a ``HeldOutError``; None: without).
        bones: pull the bone lengths towards their median.
        threads: OpenCV threads of each unit.
    """

    command: ClassVar[str] = "smooth"
    noun: ClassVar[str] = "file"
    uses_torch: ClassVar[bool] = False

    files: tuple[tuple[Path, Path, int], ...]
    outdir: Path
    error_floor: Any = None
    bones: bool = False
    threads: int = 1

    @classmethod
    def of(cls, jobs: list[tuple[Path, Path]], outdir: Path, **kwargs: Any) -> SmoothTask:
        """The task of ``(poses file, smoothed file)`` pairs (their frames read here)."""
        return cls(tuple((src, dst, poses_frames(src)) for src, dst in jobs), outdir, **kwargs)

    def outputs(self) -> dict[str, tuple[Path, int]]:
        """``<name>`` of ``<name>.poses.h5`` -> (the smoothed file, its frames)."""
        return {dst.name.removesuffix(".poses.h5"): (dst, n) for _, dst, n in self.files}

    def run_unit(self, unit: Unit, on_first: Callable[[], None]) -> None:
        """Smooth one file."""
        from freipose.predict.smooth import smooth_file

        src, dst, _ = next(f for f in self.files if f[1] == self.output(unit.session))
        on_first()
        smooth_file(src, dst, error_floor=self.error_floor, bones=self.bones)
