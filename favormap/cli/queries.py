"""The query images of ``favormap localize``: read with their priors, and the estimated poses written."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

IMAGE_EXT = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp"}


@dataclass
class Query:
    """One query image, its prior (cam_from_world; None: none given) and, once localized, its result."""

    image: Path
    prior: np.ndarray | None
    result: object = None  # LocalizationResult


def read_priors(path: Path, what: str = "priors") -> dict:
    """'NAME tx ty tz qx qy qz qw' or 'NAME m00 ... m33' (world_from_cam) per line -> cam_from_world.
    ``what`` names the file in the errors."""
    import numpy as np

    from ..errors import InputError
    from ..geometry import inverse
    from ..io.posefile import parse_pose

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{what} file not found: {path}")
    out = {}
    for ln, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        try:
            nums = np.array([float(x) for x in parts[1:]])
        except ValueError:
            raise InputError(f"{path}:{ln}: expected 'NAME' followed by 7 or 16 numbers") from None
        out[parts[0]] = inverse(parse_pose(nums, 1, f"{path}:{ln}"))
    if not out:
        raise InputError(f"{what} file {path} holds no poses")
    return out


def read_queries(args, query: Path) -> list[Query]:
    """The query images (one, or a folder's in name order) with their priors (--prior, --priors)."""
    from ..errors import InputError
    from ..io.posefile import read_pose

    if not query.is_dir():
        return [Query(query, read_pose(args.prior) if args.prior else None)]
    priors = read_priors(Path(args.priors)) if args.priors else None
    images = sorted(p for p in query.iterdir() if p.suffix.lower() in IMAGE_EXT)
    if not images:
        raise InputError(f"no images in {query}")
    queries = []
    for p in images:
        if priors is None:
            queries.append(Query(p, None))
            continue
        key = p.name if p.name in priors else (p.stem if p.stem in priors else None)
        if key is None:
            raise InputError(f"no prior for {p.name} in {args.priors}")
        queries.append(Query(p, priors[key]))
    return queries


def write_poses(path: Path, done: list[Query], one: bool) -> None:
    """--output: one query's cam_from_world as a pose file, or a line 'name world_from_cam (16 numbers)'
    per query of a folder."""
    from ..geometry import inverse
    from ..io.posefile import write_pose
    from ..mapfile import atomic_path

    if one:
        with atomic_path(path) as tmp:
            write_pose(tmp, done[0].result.cam_from_world)
    else:
        with atomic_path(path) as tmp:
            with open(tmp, "w") as fh:
                for q in done:
                    fh.write(
                        q.image.name
                        + " "
                        + " ".join(f"{v:.9g}" for v in inverse(q.result.cam_from_world).ravel())
                        + "\n"
                    )
