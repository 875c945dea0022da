"""io: posed image sequences in, images out."""

from __future__ import annotations

from pathlib import Path

from ..errors import SequenceError
from .readers import READERS
from .types import Camera, Frame, Sequence

_IMAGES = ("load_image", "prepare_image", "read_rgb", "working_camera")


def __getattr__(name):
    # the image functions need OpenCV: imported on first use, so that commands that only read maps
    # (info, validate, query) do not pay for it
    if name in _IMAGES:
        from . import images

        return getattr(images, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "Camera",
    "Frame",
    "Sequence",
    "read_sequence",
    "detect_format",
    "load_image",
    "prepare_image",
    "read_rgb",
    "working_camera",
    "READERS",
]


def detect_format(root: Path) -> str:
    root = Path(root)
    for name, mod in READERS.items():
        if mod.detect(root):
            return name
    raise SequenceError(
        f"cannot recognise the sequence format of {root} (supported: {', '.join(READERS)}); use --format"
    )


def detect_format_or_none(root: Path) -> str | None:
    return next((name for name, mod in READERS.items() if mod.detect(Path(root))), None)


def descriptor_files(root: Path) -> set[str]:
    """Names of the files in ``root`` that describe a sequence (transforms.json, poses_bounds.npy, ...)
    of the format detected there: the files a user may give instead of the folder."""
    name = detect_format_or_none(root)
    if name is None:
        return set()
    files = getattr(READERS[name], "DESCRIPTOR_FILES", ())
    return {f.name for pattern in files for f in Path(root).glob(pattern) if f.is_file()}


def read_sequence(root, format: str | None = None) -> Sequence:
    """Read a posed image sequence. ``format`` is auto-detected when None."""
    root = Path(root)
    if not root.exists():
        raise SequenceError(f"sequence not found: {root}")
    if root.is_file():
        # pointing at the descriptor file itself (transforms.json, sequence.json, ...) is fine;
        # any other file (an image, a map) is named as given, not as the folder above it
        if root.name not in descriptor_files(root.parent):
            raise SequenceError(
                f"{root} is a file, not a sequence: give the folder that holds the images and poses"
                + (f" ({root.parent})" if detect_format_or_none(root.parent) else "")
            )
        root = root.parent
    if not any(root.iterdir()):
        raise SequenceError(f"sequence folder is empty: {root}")
    name = format or detect_format(root)
    if name not in READERS:
        raise SequenceError(f"unknown sequence format {name!r} (supported: {', '.join(READERS)})")
    seq = READERS[name].read(root)
    if not seq.frames:
        raise SequenceError(f"sequence {root} has no frames")
    missing = [f.name for f in seq.frames if not Path(f.image_path).is_file()]
    if missing:
        raise SequenceError(f"{len(missing)} image(s) of {root} are missing, e.g. {missing[0]}")
    return seq
