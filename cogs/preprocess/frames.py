"""Step 1: decode the input (a video file through PyAV, or a folder of images) into RGB frames.

Frames are taken every ``stride``-th, at most ``limit`` of them, and shrunk so the longer
side is at most ``max_side`` pixels (never enlarged). Width and height are rounded down to
even numbers so the frames re-encode as video without padding.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cogs.errors import UserError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")


@dataclass
class Frames:
    images: np.ndarray  # [T, H, W, 3] uint8 RGB
    fps: float  # of the kept frames (source fps / stride)
    source_indices: np.ndarray  # [T] index of each kept frame in the source
    source_size: tuple[int, int]  # (width, height) before resizing

    @property
    def n(self) -> int:
        return len(self.images)

    @property
    def height(self) -> int:
        return self.images.shape[1]

    @property
    def width(self) -> int:
        return self.images.shape[2]


def output_size(width: int, height: int, max_side: int | None) -> tuple[int, int]:
    """(width, height) after shrinking to ``max_side`` (even numbers, aspect kept)."""
    s = 1.0 if not max_side or max(width, height) <= max_side else max_side / max(width, height)
    w = max(2, int(round(width * s)) // 2 * 2)
    h = max(2, int(round(height * s)) // 2 * 2)
    return w, h


def _resize(rgb: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    if (rgb.shape[1], rgb.shape[0]) == size:
        return rgb
    import cv2

    return cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)


def read_frames(
    source: str | Path,
    stride: int = 1,
    limit: int | None = None,
    max_side: int | None = 960,
    start: int = 0,
    on_frame=None,
) -> Frames:
    """Decode ``source`` (video file or image folder); ``on_frame(k)`` is called per kept frame.

    Raises UserError when the source is missing, unreadable or holds no frame.
    """
    source = Path(source)
    if stride < 1:
        raise UserError(f"--stride must be >= 1, got {stride}")
    if limit is not None and limit < 1:
        raise UserError(f"--limit must be >= 1, got {limit}")
    if not source.exists():
        raise UserError(f"input {source} does not exist")
    if source.is_dir():
        return _read_folder(source, stride, limit, max_side, start, on_frame)
    return _read_video(source, stride, limit, max_side, start, on_frame)


def probe(source: str | Path, stride: int = 1, limit: int | None = None, start: int = 0) -> tuple[int | None, tuple[int, int] | None]:
    """(how many frames ``read_frames`` would keep, (width, height) of the source) from the
    folder listing and the first image's header, or the video's stream header; None for
    what cannot be told without decoding (a stream that does not state its frame count,
    an unreadable file: ``read_frames`` reports those). Used to check the object prompts
    before any work."""
    source = Path(source)
    n_source, size = None, None
    try:
        if source.is_dir():
            from PIL import Image

            files = sorted(p for p in source.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith("."))
            n_source = len(files)
            if files:
                with Image.open(files[0]) as im:
                    size = (int(im.width), int(im.height))
                    if im.getexif().get(0x0112) in (5, 6, 7, 8):  # EXIF orientations with a quarter turn
                        size = size[::-1]
        elif source.is_file():
            import av

            with av.open(str(source)) as c:
                if c.streams.video:
                    st = c.streams.video[0]
                    n_source = int(st.frames) or None
                    size = (int(st.width), int(st.height)) if st.width and st.height else None
                    if size and round(display_rotation(source) / 90.0) % 2:
                        size = size[::-1]
    except Exception:  # whatever is wrong with the input, read_frames says it better
        return None, None
    if n_source is None:
        return None, size
    n = max(0, (n_source - start + stride - 1) // stride)
    return (min(n, limit) if limit else n), size


def upright(rgb: np.ndarray, rotation: float, where: str = "") -> np.ndarray:
    """The frame as a player shows it: a video's display matrix (phones store a portrait
    clip as landscape pixels with a quarter turn in its header) rotates the decoded pixels
    counter-clockwise by ``rotation`` degrees (PyAV's ``VideoFrame.rotation``). Quarter
    turns only; another angle is left as decoded, with a warning."""
    k = round(rotation / 90.0)
    if abs(rotation - 90.0 * k) > 1.0:
        import logging

        logging.getLogger(__name__).warning("%s: display rotation of %g degrees is not a quarter turn; frames kept as "
                                            "stored", where, rotation)
        return rgb
    return np.ascontiguousarray(np.rot90(rgb, k % 4)) if k % 4 else rgb


def display_rotation(path: str | Path) -> float:
    """The counter-clockwise turn (degrees) a video's display matrix asks for, read from its
    first frame (0 for a folder, a video without one, or one that cannot be decoded)."""
    path = Path(path)
    if not path.is_file():
        return 0.0
    try:
        import av

        with av.open(str(path)) as c:
            if not c.streams.video:
                return 0.0
            first = next(c.decode(c.streams.video[0]), None)
            return 0.0 if first is None else _rotation(first)
    except Exception:  # read_frames reports an unreadable input
        return 0.0


def _rotation(frame) -> float:
    try:
        return float(frame.rotation or 0.0)
    except (AttributeError, TypeError, ValueError):  # no display matrix
        return 0.0


def _keep(i: int, start: int, stride: int) -> bool:
    return i >= start and (i - start) % stride == 0


def _read_video(path: Path, stride, limit, max_side, start, on_frame) -> Frames:
    import av

    try:
        container = av.open(str(path))
    except (av.error.FFmpegError, UnicodeDecodeError, OSError) as e:
        raise UserError(f"cannot open video {path}: {e}") from None
    images, idx = [], []
    with container:
        if not container.streams.video:
            raise UserError(f"{path} holds no video stream")
        stream = container.streams.video[0]
        rate = stream.average_rate or stream.guessed_rate
        fps = float(rate) if rate else 30.0
        size = None
        try:
            for i, frame in enumerate(container.decode(stream)):
                if not _keep(i, start, stride):
                    continue
                rgb = upright(frame.to_ndarray(format="rgb24"), _rotation(frame), str(path))
                if size is None:
                    src_size = (rgb.shape[1], rgb.shape[0])
                    size = output_size(*src_size, max_side)
                images.append(_resize(rgb, size))
                idx.append(i)
                if on_frame:
                    on_frame(len(images))
                if limit and len(images) >= limit:
                    break
        except av.error.FFmpegError as e:
            if not images:
                raise UserError(f"cannot decode video {path}: {e}") from None
            # A truncated file: keep the frames decoded so far.
    if not images:
        raise UserError(f"video {path} yielded no frames (start={start}, stride={stride})")
    return Frames(np.stack(images), fps / stride, np.array(idx), src_size)


def _read_folder(path: Path, stride, limit, max_side, start, on_frame) -> Frames:
    from PIL import Image, ImageOps, UnidentifiedImageError

    files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith("."))
    if not files:
        raise UserError(f"folder {path} holds no images ({', '.join(IMAGE_SUFFIXES)})")
    files = [f for i, f in enumerate(files) if _keep(i, start, stride)]
    if limit:
        files = files[:limit]
    if not files:
        raise UserError(f"folder {path}: no image left after start={start}, stride={stride}")
    images, size, src_size = [], None, None
    for k, f in enumerate(files):
        try:
            with Image.open(f) as im:  # upright by its EXIF orientation, as viewers show it (phone photos)
                rgb = np.asarray(ImageOps.exif_transpose(im).convert("RGB"))
        except (UnidentifiedImageError, OSError) as e:
            raise UserError(f"cannot read image {f}: {e}") from None
        if size is None:
            src_size = (rgb.shape[1], rgb.shape[0])
            size = output_size(*src_size, max_side)
        elif (rgb.shape[1], rgb.shape[0]) != src_size:
            raise UserError(
                f"image {f} is {rgb.shape[1]}x{rgb.shape[0]} but {files[0].name} is {src_size[0]}x{src_size[1]}; "
                "all frames must have one size"
            )
        images.append(_resize(rgb, size))
        if on_frame:
            on_frame(k + 1)
    idx = np.array([start + i * stride for i in range(len(images))])
    return Frames(np.stack(images), 30.0 / stride, idx, src_size)


def write_video(path: str | Path, frames: np.ndarray, fps: float = 12.0, crf: int = 12) -> None:
    """Encode [T, H, W, 3] uint8 frames as an H.264 MP4 (used by tests and benchmarks).

    The same frames give the same video on every machine and every run, so that the
    accuracy benchmark's runs are comparable: one encoder thread (libx264's output depends
    on its thread count, which by default follows the CPUs the process may use: decoded
    frames 36-43 grey levels apart between 1, 2 and 4 threads) and no macroblock-tree
    rate control (its lookahead reads memory it never wrote, so repeated encodes of the
    synthetic scene's frames decoded up to 33 grey levels apart).
    """
    import av
    from fractions import Fraction

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    T, H, W, _ = frames.shape
    with av.open(str(path), mode="w") as out:
        stream = out.add_stream("libx264", rate=Fraction(fps).limit_denominator(1000))
        stream.width, stream.height = W - W % 2, H - H % 2
        stream.pix_fmt = "yuv420p"
        stream.options = {"crf": str(crf), "threads": "1", "x264-params": "mbtree=0"}
        for rgb in frames:
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb[: stream.height, : stream.width]), format="rgb24")
            for packet in stream.encode(frame):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
