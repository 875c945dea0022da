"""The project's error types. Every failure a user can cause ends in one of these."""


def first_line(e: BaseException) -> str:
    """The first line of an exception's message (its type name when the message is empty): for
    one-line error reports of foreign exceptions (h5py, trimesh, rerun, ...)."""
    s = str(e).strip()
    return s.splitlines()[0] if s else type(e).__name__


class FavormapError(Exception):
    """Base class: the CLI prints ``favormap: error: <message>`` and exits non-zero."""

    exit_code = 1


class InputError(FavormapError):
    """Bad user input: missing files, unreadable images, malformed pose or camera files."""


class SequenceError(InputError):
    """A posed image sequence that cannot be read (unknown format, missing poses, ...)."""


class MapFormatError(FavormapError):
    """A file that is not a valid favormap map (foreign, truncated, corrupted, wrong version)."""


class IncompatibleMapsError(FavormapError):
    """Maps that cannot be combined (different extractor, channels, grid or patch size)."""


class LocalizationFailed(FavormapError):
    """A query that could not be localized (too few matches or inliers)."""

    exit_code = 2
