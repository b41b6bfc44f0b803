"""``freipose render --executor ...``: the overlay video as one unit.

An overlay video is one encoded stream; parts encoded apart and joined would not be the
bytes of a single run (the encoder's state carries over between frames), so the video is
not cut: the unit renders it as a single run does, on the node the executor gives it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from freipose.cluster.driver import Unit
from freipose.cluster.stages import FileJob, WholeOutputs


@dataclass(frozen=True)
class RenderTask(FileJob, WholeOutputs):
    """Everything the unit of one ``render`` needs (pickled into its job).

    Attributes:
        poses: the poses file.
        videos: the videos of the cameras shown, in order.
        rig: their cameras (a ``CameraRig``).
        out_path: the overlay video to write.
        frames: ``(start, stop)`` video frame numbers (None: all).
        n_frames: frames drawn.
        tile_width: width of each view in pixels.
        show_3d: draw the 3D skeleton panel.
        threads: OpenCV threads of the unit.
    """

    command: ClassVar[str] = "render"
    noun: ClassVar[str] = "video"
    uses_torch: ClassVar[bool] = False

    poses: Path
    videos: tuple[Path, ...]
    rig: Any
    out_path: Path
    frames: tuple[int, int] | None
    n_frames: int
    tile_width: int
    show_3d: bool
    threads: int = 1

    def outputs(self) -> dict[str, tuple[Path, int]]:
        """The video's name -> (the video, its frames)."""
        return {self.out_path.name: (self.out_path, self.n_frames)}

    def run_unit(self, unit: Unit, on_first: Callable[[], None]) -> None:
        """Render the video (under its lock, leftovers of a stopped job removed)."""
        from freipose.io.atomic import remove_leftover_partials
        from freipose.io.lock import output_lock
        from freipose.io.poses import read_poses_h5
        from freipose.predict.render import render_overlay

        data = read_poses_h5(self.poses)
        out = self.out_path
        with output_lock(out, "overlay video"):
            remove_leftover_partials(out, out.suffix.lower())
            remove_leftover_partials(out)
            on_first()
            render_overlay(list(self.videos), self.rig, data, out, frames=self.frames,
                           tile_width=self.tile_width, show_3d=self.show_3d,
                           progress=False)  # fmt: skip
