"""Video and image-folder input/output, with clear errors for unreadable media.

A *frame source* is a video file or a folder of images (sorted by name, numbers
numerically); both give BGR uint8 frames (H, W, 3) by index, decoded by OpenCV. Writers
encode to a temporary name and rename on close; H.264 (videos for people to watch) goes
through the ffmpeg binary of ``imageio-ffmpeg``, the other codecs through OpenCV.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import shutil
import subprocess
import tempfile
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from pathlib import Path
from types import TracebackType

import cv2
import numpy as np

from freipose.errors import FreiPoseError, OutputWriteError, filesystem_message
from freipose.io.atomic import output_errors
from freipose.io.natsort import natural_key

log = logging.getLogger(__name__)

VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov", ".m4v", ".mpg", ".mpeg", ".wmv")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
# FourCC per suffix for writing; .mkv is lossless (FFV1).
FOURCC = {".mp4": "mp4v", ".avi": "MJPG", ".mkv": "FFV1"}
#: free bytes below which a video that cannot be read back was cut short by a full disk
_FULL_BYTES = 1_000_000


class MediaError(FreiPoseError):
    """A video or image folder cannot be read; the message names it and says why."""


class FrameRangeError(FreiPoseError):
    """A ``--frames START:STOP`` range is malformed or selects no frame."""


@contextlib.contextmanager
def opencv_threads(n: int) -> Iterator[None]:
    """Run the block with ``n`` OpenCV threads and give the caller's setting back after it.

    The setting is process-wide: work spread over processes wants one thread each.
    """
    before = cv2.getNumThreads()
    cv2.setNumThreads(int(n))
    try:
        yield
    finally:
        cv2.setNumThreads(before)


def frame_range(spec: str | None, num_frames: int) -> range:
    """Frame range ``START:STOP`` (Python slice semantics, no step) clipped to the video.

    ``None`` or ``""`` is the whole video; ``START:`` and ``:STOP`` are accepted; negative
    values count from the end. A STOP past the end is clipped (with a warning).

    Raises:
        FrameRangeError: malformed spec or an empty range.
    """
    if not spec:
        return range(num_frames)
    parts = str(spec).split(":")
    if len(parts) != 2:
        raise FrameRangeError(
            f"--frames must look like START:STOP (e.g. 0:1000 or 500:), got {spec!r}"
        )
    try:
        a = int(parts[0]) if parts[0].strip() else None
        b = int(parts[1]) if parts[1].strip() else None
    except ValueError:
        raise FrameRangeError(f"--frames must be two integers START:STOP, got {spec!r}") from None
    r = range(num_frames)[slice(a, b)]
    if b is not None and b > num_frames:
        log.warning(
            "--frames %s: the videos have only %d frames; stopping at %d",
            spec,
            num_frames,
            num_frames,
        )
    if len(r) == 0:
        raise FrameRangeError(
            f"--frames {spec!r} selects no frames of a {num_frames}-frame video; "
            f"give START < STOP within 0..{num_frames}"
        )
    return r


def find_video(stem: str, folders: Sequence[str | Path]) -> Path | None:
    """The first ``folder/<stem><suffix>`` video file, or None.

    Folders are tried in order, and in each the suffixes in :data:`VIDEO_SUFFIXES` order.
    """
    for folder in folders:
        for sfx in VIDEO_SUFFIXES:
            p = Path(folder) / f"{stem}{sfx}"
            if p.is_file():
                return p
    return None


def list_images(folder: str | Path) -> list[Path]:
    """The images of a folder in frame-source order (by name, numbers numerically).

    Frame ``i`` of :class:`FrameSource` on ``folder`` is element ``i``; hidden files are skipped.
    """
    folder = Path(folder)
    imgs = (
        p
        for p in folder.iterdir()
        if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".")
    )
    return sorted(imgs, key=lambda p: natural_key(p.name))


class FrameSource:
    """Random and sequential access to the frames of a video file or an image folder.

    Args:
        path: a video file or a folder of images.
        cache_size: how many decoded frames to keep (least recently used).
    """

    def __init__(self, path: str | Path, cache_size: int = 0):
        self.path = Path(path)
        self.cache_size = cache_size
        self._cache: OrderedDict[int, np.ndarray] = OrderedDict()
        self._cap: cv2.VideoCapture | None = None
        self._next = 0  # index the capture will return next
        self._images: list[Path] | None = None
        if not self.path.exists():
            raise MediaError(f"{self.path}: no such video file or image folder")
        if self.path.is_dir():
            imgs = list_images(self.path)
            if not imgs:
                raise MediaError(
                    f"{self.path}: the folder holds no images ({', '.join(IMAGE_SUFFIXES)})"
                )
            self._images = imgs
            first = cv2.imread(str(imgs[0]), cv2.IMREAD_COLOR)
            if first is None:
                raise MediaError(f"{imgs[0]}: cannot be read as an image")
            self.height, self.width = first.shape[:2]
            self.num_frames = len(imgs)
            self.fps = float("nan")
        else:
            cap = self._open()
            ok, first = cap.read()
            if not ok or first is None:
                raise MediaError(
                    f"{self.path}: OpenCV cannot decode a frame; the file is not a video, is "
                    f"corrupt, or uses a codec this OpenCV build lacks"
                )
            self._next = 1
            self.height, self.width = first.shape[:2]
            n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
            self.num_frames = n if n > 0 else self._count_frames()
            fps = float(cap.get(cv2.CAP_PROP_FPS))
            self.fps = fps if fps > 0 else float("nan")
            self._put(0, first)

    @property
    def name(self) -> str:
        """The camera name: the file or folder stem."""
        return self.path.stem if self.path.is_file() else self.path.name

    @property
    def size(self) -> tuple[int, int]:
        """The frame size ``(width, height)``."""
        return self.width, self.height

    def _open(self) -> cv2.VideoCapture:
        cap = cv2.VideoCapture(str(self.path))
        self._cap = cap
        if not cap.isOpened():
            raise MediaError(f"{self.path}: OpenCV cannot open this file as a video")
        self._next = 0
        return cap

    def _count_frames(self) -> int:
        cap = cv2.VideoCapture(str(self.path))
        n = 0
        while cap.grab():
            n += 1
        cap.release()
        return n

    def _put(self, i: int, frame: np.ndarray) -> None:
        if self.cache_size > 0:
            frame.setflags(write=False)  # shared by every later read of the frame
            self._cache[i] = frame
            self._cache.move_to_end(i)
            while len(self._cache) > self.cache_size:
                self._cache.popitem(last=False)

    def __len__(self) -> int:
        return self.num_frames

    def read(self, index: int) -> np.ndarray:
        """Frame ``index`` as BGR uint8 (H, W, 3); read-only when the source caches frames.

        Raises:
            IndexError: the index is outside the video.
            MediaError: the frame cannot be decoded (e.g. a truncated file).
        """
        if not 0 <= index < self.num_frames:
            raise IndexError(f"{self.path}: frame {index} is outside 0..{self.num_frames - 1}")
        if index in self._cache:
            self._cache.move_to_end(index)
            return self._cache[index]
        if self._images is not None:
            frame = cv2.imread(str(self._images[index]), cv2.IMREAD_COLOR)
            if frame is None:
                raise MediaError(f"{self._images[index]}: cannot be read as an image")
        else:
            cap = self._cap if self._cap is not None else self._open()
            if index != self._next:
                if index < self._next or index - self._next > 32:
                    cap.set(cv2.CAP_PROP_POS_FRAMES, index)
                    self._next = index
                while self._next < index:  # short forward skips: grab is exact and cheap
                    if not cap.grab():
                        break
                    self._next += 1
            ok, frame = cap.read()
            if not ok or frame is None:
                raise MediaError(f"{self.path}: frame {index} cannot be decoded (truncated file?)")
            self._next = index + 1
        self._put(index, frame)
        return frame

    def __getitem__(self, index: int) -> np.ndarray:
        return self.read(index)

    def close(self) -> None:
        """Release the video file (a later read opens it again)."""
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    def __enter__(self) -> FrameSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class VideoWriter:
    """Write BGR uint8 frames to a video; the file appears under its name only on ``close``.

    ``codec="h264"`` writes H.264 in MP4 (yuv420p, ``+faststart``) through the ffmpeg binary
    that ``imageio-ffmpeg`` ships: the video plays in web browsers. An odd width or height
    is padded by one black pixel row or column. The other codecs go through OpenCV.

    Args:
        path: output file; the suffix picks the codec unless ``codec`` is given (.mp4 mp4v,
            .avi MJPG, .mkv lossless FFV1).
        fps: frame rate.
        size: (width, height) of the frames passed to :meth:`write`.
        codec: ``"h264"`` (an .mp4 that browsers play) or None (the suffix's codec).
    """

    def __init__(
        self, path: str | Path, fps: float, size: tuple[int, int], codec: str | None = None
    ):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        sfx = self.path.suffix.lower()
        if codec not in (None, "h264"):
            raise MediaError(f"{self.path}: unknown codec {codec!r}; use 'h264' or None")
        if sfx not in FOURCC or (codec == "h264" and sfx != ".mp4"):
            allowed = [".mp4"] if codec == "h264" else sorted(FOURCC)
            raise MediaError(f"{self.path}: cannot write {sfx!r} videos; use one of {allowed}")
        self._tmp = self.path.with_name(f".{self.path.stem}.partial{sfx}")
        self.size = (int(size[0]), int(size[1]))
        self.codec = codec or FOURCC[sfx]
        self._w: cv2.VideoWriter | _FFmpegH264 | None
        if codec == "h264":
            self._w = _FFmpegH264(self._tmp, fps, self.size)
        else:
            fourcc = cv2.VideoWriter.fourcc(*FOURCC[sfx])
            self._w = cv2.VideoWriter(str(self._tmp), fourcc, float(fps), self.size)
            if not self._w.isOpened():
                raise MediaError(f"{self.path}: OpenCV cannot open a {FOURCC[sfx]} writer")
        self.frames = 0

    def write(self, frame: np.ndarray) -> None:
        """Append one frame (H, W, 3) BGR or (H, W) gray uint8."""
        f = np.asarray(frame)
        if f.ndim == 2:
            f = cv2.cvtColor(f, cv2.COLOR_GRAY2BGR)
        if (f.shape[1], f.shape[0]) != self.size or f.dtype != np.uint8:
            raise ValueError(f"frame must be uint8 of size {self.size}, got {f.dtype} {f.shape}")
        if self._w is None:
            raise MediaError(f"{self.path}: the writer is closed")
        self._w.write(np.ascontiguousarray(f))
        self.frames += 1

    def close(self) -> None:
        """Finish the video and move it to its name.

        Raises:
            OutputWriteError: the disk filled up (the video is not complete; nothing
                appears under its name).
            MediaError: the encoder failed, or the written video cannot be read back.
        """
        if self._w is not None:
            w, self._w = self._w, None
            try:
                w.release()
                if not isinstance(w, _FFmpegH264):  # OpenCV says nothing when a write fails
                    self._check_written()
            except MediaError as exc:
                self._tmp.unlink(missing_ok=True)
                if shutil.disk_usage(self.path.parent).free < _FULL_BYTES:
                    err = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self.path))
                    raise OutputWriteError(
                        filesystem_message(err) or str(exc), errno.ENOSPC, self.path
                    ) from exc
                raise
            with output_errors(self.path, self._tmp):
                os.replace(self._tmp, self.path)

    def _check_written(self) -> None:
        """Raise unless the temporary file opens and its last frame decodes."""
        cap = cv2.VideoCapture(str(self._tmp))
        try:
            ok = cap.isOpened()
            if ok and self.frames:
                cap.set(cv2.CAP_PROP_POS_FRAMES, self.frames - 1)
                ok = cap.read()[0]
        finally:
            cap.release()
        if not ok:
            raise MediaError(f"{self.path}: the written video cannot be read back")

    def abort(self) -> None:
        """Stop writing and remove the partial file (nothing appears under the name)."""
        if self._w is not None:
            w, self._w = self._w, None
            if isinstance(w, _FFmpegH264):
                w.kill()
            else:
                w.release()
        self._tmp.unlink(missing_ok=True)

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def _ffmpeg_exe(path: Path) -> str:
    """The ffmpeg binary of ``imageio-ffmpeg`` (or ``IMAGEIO_FFMPEG_EXE``)."""
    try:
        import imageio_ffmpeg

        return str(imageio_ffmpeg.get_ffmpeg_exe())
    except (ImportError, RuntimeError) as e:
        raise MediaError(
            f"{path}: writing H.264 needs the ffmpeg binary of imageio-ffmpeg ({e}); install it "
            "with `pip install imageio-ffmpeg`, or write a .mkv (lossless) or .avi video instead"
        ) from None


class _FFmpegH264:
    """An ffmpeg process encoding raw BGR frames from its standard input to H.264 MP4."""

    def __init__(self, path: Path, fps: float, size: tuple[int, int]):
        self.path = path
        self.frame_bytes = size[0] * size[1] * 3
        cmd = [
            _ffmpeg_exe(path), "-y", "-nostdin", "-loglevel", "error",
            "-f", "rawvideo", "-pix_fmt", "bgr24", "-s", f"{size[0]}x{size[1]}",
            "-r", f"{float(fps):g}", "-i", "pipe:0", "-an",
            "-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2", "-c:v", "libx264", "-preset", "fast",
            "-crf", "20", "-pix_fmt", "yuv420p", "-movflags", "+faststart",
            "-f", "mp4", str(path),
        ]  # fmt: skip
        self._err = tempfile.TemporaryFile()  # noqa: SIM115 - lives as long as the encoder
        try:
            self._proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stderr=self._err)
        except OSError as e:
            self._err.close()
            raise MediaError(f"{path}: cannot start the H.264 encoder {cmd[0]}: {e}") from None

    def _message(self) -> str:
        self._err.seek(0)
        text = self._err.read().decode(errors="replace").strip()
        return text.splitlines()[-1] if text else f"exit status {self._proc.returncode}"

    def write(self, frame: np.ndarray) -> None:
        """Send one BGR frame (H, W, 3) uint8 to the encoder."""
        stdin = self._proc.stdin
        if stdin is None:
            raise MediaError(f"{self.path}: the H.264 encoder has no input pipe")
        try:
            stdin.write(frame.tobytes())
        except (BrokenPipeError, OSError):
            self._proc.wait()
            raise MediaError(f"{self.path}: the H.264 encoder stopped: {self._message()}") from None

    def release(self) -> None:
        """Close the input and wait for the encoder; raises MediaError if it failed."""
        if self._proc.stdin is not None:
            with contextlib.suppress(BrokenPipeError, OSError):
                self._proc.stdin.close()
        rc = self._proc.wait()
        msg = self._message() if rc != 0 else ""
        self._err.close()
        if rc != 0:
            raise MediaError(f"{self.path}: the H.264 encoder failed: {msg}")

    def kill(self) -> None:
        """Stop the encoder without finishing the file."""
        if self._proc.stdin is not None:
            with contextlib.suppress(BrokenPipeError, OSError):
                self._proc.stdin.close()
        self._proc.kill()
        self._proc.wait()
        self._err.close()


def _is_camera_video(p: Path) -> bool:
    """Whether ``p`` is a (not hidden) video file of a session."""
    return p.suffix.lower() in VIDEO_SUFFIXES and not p.name.startswith(".") and p.is_file()


def find_camera_videos(folder: str | Path) -> dict[str, Path]:
    """Videos of a session folder, keyed by camera name, in the order of their names.

    A camera's video is ``<camera>.<ext>`` in the folder (the camera is the file stem) or the
    one video inside a folder named after the camera (``<camera>/<any name>.<ext>``,
    sleap-anipose's layout, which keeps the camera's labels beside its video). Subfolders
    without videos (labels) are not cameras, nor, in a folder with videos of its own,
    subfolders with several videos (the board videos of a ``calibration`` folder).

    Args:
        folder: the session folder.

    Returns:
        Camera name -> video file.

    Raises:
        MediaError: not a folder, no video, a camera folder with several videos, or a
            camera with both a video in the session folder and a camera folder.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise MediaError(f"{folder}: not a folder; a session is a folder with one video per camera")
    vids: dict[str, Path] = {}
    flat = any(_is_camera_video(p) for p in folder.iterdir())
    for p in sorted(folder.iterdir()):
        if p.is_dir() and not p.name.startswith("."):
            inside = [q for q in sorted(p.iterdir()) if _is_camera_video(q)]
            if len(inside) > 1 and flat:  # e.g. the board videos of a calibration folder
                continue
            if len(inside) > 1:
                raise MediaError(
                    f"{p}: {len(inside)} videos ({', '.join(q.name for q in inside)}) in the "
                    f"folder of camera {p.name!r}; a camera folder holds one video. Move the "
                    f"others out, or put each camera's video in the session folder as "
                    f"<camera>{inside[0].suffix}"
                )
            cam, video = p.name, inside[0] if inside else None
        else:
            cam, video = p.stem, p if _is_camera_video(p) else None
        if video is None:
            continue
        if cam in vids:
            raise MediaError(
                f"{folder}: camera {cam!r} has two videos, {vids[cam]} and {video}; keep "
                f"<camera>.<ext> in the session folder or <camera>/<video> in a camera folder, "
                "not both"
            )
        vids[cam] = video
    if not vids:
        raise MediaError(
            f"{folder}: no videos found ({', '.join(VIDEO_SUFFIXES)}); a session holds one "
            "video per camera, as <camera>.<ext> or <camera>/<video>.<ext>"
        )
    return vids
