"""``freipose detect --executor ...``: a session's frames as units, their boxes joined.

The session's frame range is cut into units of ``chunk_frames`` frames, rounded up to whole
batches of ``batch_size`` and counted from the range's start, so every frame meets the box
source in the batch of a single run. Every unit builds the box source over the whole range
(the background of ``bgsub`` is the median of the same frames as in a single run) and
detects its frames into ``<folder>/.jobs/<name>/parts/I-of-N.boxes.h5`` under that part's
lock; a stopped unit resumes from its progress file. When all parts are there they are
joined into the output, checked (every frame of the range exactly once, in order), and
removed: the joined file equals a single ``freipose detect`` run's output value for value.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from freipose.cluster.driver import Unit
from freipose.cluster.stages import FileJob
from freipose.errors import FreiPoseError
from freipose.io.session import Session
from freipose.io.video import frame_range


@dataclass(frozen=True)
class DetectTask(FileJob):
    """Everything every unit of one detection needs (pickled into each job).

    Attributes:
        session: the session, opened with the calibration's cameras.
        out_path: the boxes file to write.
        frames: ``START:STOP`` (None: all frames).
        model: the detector checkpoint (method ``detector``).
        method: ``detector``, ``bgsub``, ``fixed`` or None (from ``model``/``fixed_boxes``).
        fixed_boxes: the TOML of fixed boxes (method ``fixed``).
        device: where the detector runs.
        bg_samples: frames per camera of the median background (``bgsub``).
        cube_size: edge in mm of the cube whose projection gives the crop boxes.
        min_views: fewest agreeing views for a 3D centre.
        batch_size: time instants per batch.
        chunk_frames: frames per unit (rounded up to whole batches).
        threads: PyTorch and OpenCV threads of each unit.
    """

    command: ClassVar[str] = "detect"
    noun: ClassVar[str] = "session"
    uses_torch: ClassVar[bool] = True

    session: Session
    out_path: Path
    frames: str | None
    model: Path | None
    method: str | None
    fixed_boxes: Path | None
    device: str
    bg_samples: int
    cube_size: float
    min_views: int
    batch_size: int
    chunk_frames: int
    threads: int

    def frame_range(self) -> range:
        """The frames of the whole detection."""
        return frame_range(self.frames, self.session.num_frames)

    def _rows(self) -> int:
        """Frames per unit: ``chunk_frames`` rounded up to whole batches."""
        from freipose.predict.run import commit_rows

        return commit_rows(self.batch_size, self.chunk_frames)

    def plan_units(self) -> list[Unit]:
        """The range cut into whole-batch chunks."""
        n = max(1, -(-len(self.frame_range()) // self._rows()))
        name = self.session.name
        return [Unit(f"{name}.{i}-of-{n}", name, i, n, len(self._frames_of(i))) for i in range(n)]

    def _frames_of(self, index: int) -> range:
        rows = self._rows()
        return self.frame_range()[index * rows : (index + 1) * rows]

    def part(self, unit: Unit) -> Path:
        """The boxes file unit ``unit`` writes."""
        return self.root / "parts" / f"{unit.index}-of-{unit.count}.boxes.h5"

    def output(self, group: str) -> Path:
        """The boxes file (one session: one output)."""
        return self.out_path

    def output_done(self, group: str) -> bool:
        """Whether the boxes file exists (it is written whole, under a temporary name)."""
        return self.out_path.is_file()

    def unit_is_done(self, unit: Unit) -> bool:
        """Whether the unit's part (or the joined boxes file) exists."""
        return self.output_done(unit.session) or self.part(unit).is_file()

    def run_unit(self, unit: Unit, on_first: Callable[[], None]) -> None:
        """Detect the unit's frames into its part (resumable through its progress file)."""
        from freipose.detect.multiview import ConsistencyConfig
        from freipose.detect.pipeline import detect_session, make_source, open_sources
        from freipose.io.atomic import remove_leftover_partials
        from freipose.io.boxes import write_boxes_h5
        from freipose.io.lock import output_lock

        part = self.part(unit)
        part.parent.mkdir(parents=True, exist_ok=True)
        progress = part.with_name(f".{part.name}.progress.npz")
        sources = open_sources(self.session)
        try:
            rig = self.session.rig
            source, method, desc = make_source(
                rig, sources, self.frame_range(), self.model, self.method, self.fixed_boxes,
                self.device, self.bg_samples,
            )  # fmt: skip
            cfg = ConsistencyConfig(cube_size=self.cube_size, min_views=self.min_views)
            with output_lock(part, "boxes part"):
                if part.is_file():
                    return
                remove_leftover_partials(part)
                remove_leftover_partials(progress)
                on_first()
                data = detect_session(rig, sources, self._frames_of(unit.index), source, cfg,
                                      self.batch_size, method, desc,
                                      progress_file=progress)  # fmt: skip
                write_boxes_h5(data, part)
                progress.unlink(missing_ok=True)
        finally:
            for s in sources.values():
                s.close()

    def join(self, group: str, units: Sequence[Unit]) -> None:
        """Join the parts in frame order, check every frame is there once, remove them.

        Raises:
            FreiPoseError: the parts do not hold every frame of the range exactly once.
        """
        from freipose.io.boxes import BoxesData, read_boxes_h5, write_boxes_h5
        from freipose.io.lock import output_lock

        parts = [read_boxes_h5(self.part(u)) for u in sorted(units, key=lambda u: u.index)]
        frame_index = np.concatenate([p.frame_index for p in parts])
        expected = np.asarray(self.frame_range(), dtype=np.int64)
        if not np.array_equal(frame_index, expected):
            raise FreiPoseError(
                f"the parts under {self.root / 'parts'} hold {len(frame_index)} frames, not "
                f"each of the {len(expected)} frames of {self.session.name} once; remove the "
                f"folder and run the command again"
            )
        first = parts[0]
        joined = BoxesData(
            frame_index=frame_index, cameras=first.cameras,
            **{k: np.concatenate([getattr(p, k) for p in parts])
               for k in ("boxes", "scores", "agree", "n_agree", "center", "crop_boxes")},
            cube_size=first.cube_size, method=first.method, calibration=self.session.rig,
            attrs=first.attrs,
        )  # fmt: skip
        out = self.output(group)
        with output_lock(out, "boxes file"):
            write_boxes_h5(joined, out)
        shutil.rmtree(self.root / "parts", ignore_errors=True)

    def remove_outputs(self, units: Sequence[Unit]) -> None:
        """Delete the boxes file and the parts."""
        self.output(self.session.name).unlink(missing_ok=True)
        shutil.rmtree(self.root / "parts", ignore_errors=True)
