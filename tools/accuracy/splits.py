"""The benchmark's data: where the sets are (DATA, FOX), the :class:`Split` (mapping frames, queries and how a
query's error is judged), the tables of real sets, splits and suites (REAL_SETS, REAL_SPLITS, EXTRA_SPLITS,
CROSS_SPLITS, SUITES, the 7-Scenes pseudo ground truth, recall thresholds, angle bins), and the functions that
read a set and cut it into splits: fox_splits, real_splits, cross_split, with_pseudo_ground_truth and the
synthetic orbit_split, each query's angle to its nearest mapping view (nearest_view_angle)."""

from __future__ import annotations

import dataclasses
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]  # the checkout (tools/accuracy/ is two levels down)
# ../shared/data beside the checkout (or beside the folder that holds it, for a git worktree)
DATA = Path(
    os.environ.get(
        "FAVORMAP_DATA",
        next((p / "shared" / "data" for p in ROOT.parents if (p / "shared" / "data").is_dir()), ROOT.parent / "shared"),
    )
)
FOX = Path(os.environ.get("FAVORMAP_FOX", DATA / "fox"))
ANGLE_BINS = ((0, 10), (10, 20), (20, 40), (40, 180))


@dataclasses.dataclass
class Split:
    name: str
    mapping: object  # Sequence
    queries: object  # Sequence
    angle: np.ndarray | None = None  # per query: rotation to the nearest mapping view (deg)
    map_name: str | None = None  # the map (and baseline) files: another split's of the same mapping frames
    path_extent: float | None = None  # real sets: bounding-box diagonal of all the set's camera centres (units)
    units: str = "units"
    recall: tuple = ()  # real sets: (translation, rotation deg) recall thresholds in the set's units
    # a false success: localized with an error above (translation in the set's units, rotation deg); None:
    # 5 % of the path extent or 5 deg
    false_success: tuple | None = None
    priors: tuple = ()  # prior modes run on this split besides --priors
    cross: bool = False  # queries from another recording than the mapping frames

    @property
    def files(self) -> str:
        return self.map_name or self.name


def fox_splits(which: list[str], extrap_step: int = 1) -> list[Split]:
    from favormap.io import read_sequence

    if not FOX.exists():
        print(f"(skipping fox splits: {FOX} not found)", file=sys.stderr)
        return []
    seq = read_sequence(FOX)
    n = len(seq)
    out = []
    if "fox-holdout" in which:
        out.append(Split("fox-holdout", seq.subset([i for i in range(n) if i % 5]), seq.subset(list(range(0, n, 5)))))
    if "fox-extrap" in which:
        half = n // 2
        out.append(Split("fox-extrap", seq.subset(list(range(half))), seq.subset(list(range(half, n, extrap_step)))))
    for s in out:
        s.angle = nearest_view_angle(s.queries, s.mapping)
    return out


# the real sets, each read as shipped (favormap.io.read_sequence): folder, units, extra recall thresholds
REAL_SETS = {
    "fox": ("fox", "units", ()),
    "fern": ("llff_fern", "units", ()),
    "7scenes": ("7scenes_redkitchen_half", "m", ((0.05, 5.0), (0.02, 2.0))),
    "office": ("phone_office_colmap64", "units", ()),
    "cup": ("phone_cup_colmap77", "units", ()),
    "castle": ("strecha_castle_p30", "m", ()),
    "dino": ("middlebury_dino", "units", ()),
}
# the splits of each real set. holdout-K: every K-th frame held out as a query (in the reader's order),
# the map from the rest (queries between mapping views); sparse: the map from every 4th frame, queries
# midway (frames 2, 6, 10, ...); extrap: the map from the first half of the path, queries from the second
REAL_SPLITS = {
    "fox-holdout": ("fox", "holdout-5"),
    "fox-extrap": ("fox", "extrap"),
    "fern-holdout": ("fern", "holdout-3"),
    "7scenes-holdout": ("7scenes", "holdout-5"),
    "7scenes-sparse": ("7scenes", "sparse"),
    "office-holdout": ("office", "holdout-5"),
    "office-sparse": ("office", "sparse"),
    "cup-holdout": ("cup", "holdout-5"),
    "cup-sparse": ("cup", "sparse"),
    "castle-holdout": ("castle", "holdout-3"),
    "dino-holdout": ("dino", "holdout-5"),
}
# 7-Scenes with the focal its file holds (585 px, the depth camera's) instead of the reader's RGB focal
# (525 px; not in a suite: the focal measurement)
# 7-Scenes with the SfM pseudo ground truth of Brachmann et al. (ICCV 2021) for the same frames, the poses the
# FaVoR paper evaluates with, instead of the KinectFusion poses the set ships with (SEVENSCENES_PGT)
EXTRA_SPLITS = {
    "7scenes-holdout-f585": ("7scenes", "holdout-5"),
    "7scenes-sparse-f585": ("7scenes", "sparse"),
    "7scenes-holdout-pgt": ("7scenes", "holdout-5"),
    "7scenes-sparse-pgt": ("7scenes", "sparse"),
}
# queries from another recording of the same place, in the same world frame: name -> (map folder, query folder,
# units, recall thresholds, false success). The ground truth of TUM RGB-D disagrees with its images by ~1-2 cm
# and ~1 deg (SOURCE.md), so a false success is an error above 10 cm or 10 deg, well beyond that
CROSS_SPLITS = {
    "tum-desk-xyz": (
        "tum_fr1_desk_xyz/rgbd_dataset_freiburg1_desk",
        "tum_fr1_desk_xyz/rgbd_dataset_freiburg1_xyz",
        "m",
        ((0.02, 2.0), (0.05, 5.0), (0.10, 10.0)),
        (0.10, 10.0),
    ),
}
# a cross-recording split whose queries are motion-blurred: name -> (the split, blur length range in px). A
# handheld camera turning at 30-100 deg/s smears a Kinect frame (~20 ms exposure, 517 px focal) over 5-20 px;
# each query gets a straight blur of a length and direction drawn once (seeded), the map and the baseline
# are the unblurred split's
BLURRED_SPLITS = {"tum-desk-xyz-blur": ("tum-desk-xyz", (6.0, 20.0))}
# the prior modes every cross-recording split runs: none, the nearest mapping frame (what image retrieval would
# give) and the noise prior
CROSS_PRIORS = ("noise", "nearest", "none")
SUITES = {
    "real": list(REAL_SPLITS) + list(CROSS_SPLITS) + list(BLURRED_SPLITS),
    "cross": list(CROSS_SPLITS) + list(BLURRED_SPLITS),
    "real-quick": ["7scenes-holdout", "cup-holdout", "castle-holdout", "dino-holdout", "fern-holdout"],
    "7scenes-pgt": ["7scenes-holdout", "7scenes-sparse", "7scenes-holdout-pgt", "7scenes-sparse-pgt"],
}
SEVENSCENES_PGT = ROOT / "tools" / "data" / "7scenes-redkitchen-sfm-pgt.txt"
# recall thresholds of every real set, as shares of its path extent (and degrees)
REAL_RECALL = ((0.005, 2.0), (0.02, 5.0))


def _natural_order(seq) -> list[int]:
    """Frame indices in the order of their names with numbers compared as numbers (IMG_2 before IMG_10):
    the capture order of a video whose reader lists the frames lexicographically."""
    import re

    def key(i):
        return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", seq.frames[i].name)]

    return sorted(range(len(seq)), key=key)


def real_splits(which: list[str]) -> list[Split]:
    """The real-data splits in ``which`` (names of REAL_SPLITS / EXTRA_SPLITS), each set read as shipped."""
    from favormap.io import read_sequence
    from favormap.io.readers import sevenscenes_flat

    out, cache = [], {}
    for name in which:
        if name in CROSS_SPLITS:
            out += cross_split(name)
            continue
        if name in BLURRED_SPLITS:
            out += blurred_split(name)
            continue
        spec = REAL_SPLITS.get(name) or EXTRA_SPLITS.get(name)
        if spec is None:
            continue
        key, kind = spec
        folder, units, extra_recall = REAL_SETS[key]
        root = DATA / folder
        if not root.exists():
            print(f"(skipping {name}: {root} not found)", file=sys.stderr)
            continue
        poses = name.rsplit("-", 1)[-1] if name.endswith(("-f585", "-pgt")) else "shipped"
        if (key, poses) not in cache:
            cache[key, poses] = (
                sevenscenes_flat.read_with_focal(root, "file")
                if poses == "f585"
                else with_pseudo_ground_truth(read_sequence(root), SEVENSCENES_PGT)
                if poses == "pgt"
                else read_sequence(root)
            )
        seq = cache[key, poses]
        n = len(seq)
        order = _natural_order(seq)
        if kind.startswith("holdout-"):
            k = int(kind.split("-")[1])
            m_idx, q_idx = [i for i in range(n) if i % k], list(range(0, n, k))
        elif kind == "sparse":
            m_idx, q_idx = [order[i] for i in range(0, n, 4)], [order[i] for i in range(2, n, 4)]
        else:  # extrap
            m_idx, q_idx = order[: n // 2], order[n // 2 :]
        centres = np.array([-f.cam_from_world[:3, :3].T @ f.cam_from_world[:3, 3] for f in seq.frames])
        ext = float(np.linalg.norm(centres.max(0) - centres.min(0)))
        recall = tuple((t * ext, r) for t, r in REAL_RECALL) + tuple(extra_recall)
        sp = Split(name, seq.subset(m_idx), seq.subset(q_idx), path_extent=ext, units=units, recall=recall)
        sp.angle = nearest_view_angle(sp.queries, sp.mapping)
        out.append(sp)
    return out


def cross_split(name: str) -> list[Split]:
    """The cross-recording split ``name`` (CROSS_SPLITS): the map from one recording as shipped, every frame of
    the other as a query; [] when the data is not there."""
    from favormap.io import read_sequence

    map_folder, query_folder, units, recall, false_success = CROSS_SPLITS[name]
    roots = [DATA / map_folder, DATA / query_folder]
    missing = [r for r in roots if not r.exists()]
    if missing:
        print(f"(skipping {name}: {missing[0]} not found)", file=sys.stderr)
        return []
    mapping, queries = (read_sequence(r) for r in roots)
    centres = np.array([-f.cam_from_world[:3, :3].T @ f.cam_from_world[:3, 3] for f in mapping.frames + queries.frames])
    ext = float(np.linalg.norm(centres.max(0) - centres.min(0)))
    sp = Split(name, mapping, queries, path_extent=ext, units=units, recall=recall, false_success=false_success)
    sp.priors, sp.cross = CROSS_PRIORS, True
    sp.angle = nearest_view_angle(queries, mapping)
    return [sp]


def blurred_split(name: str, seed: int = 0) -> list[Split]:
    """The cross-recording split of BLURRED_SPLITS ``name``: its base split with every query image blurred
    along a straight line (length and direction drawn per query from ``seed``), the images written once to a
    folder under the temporary directory; the map and baseline files are the base split's."""
    import tempfile

    import cv2

    base, (lo, hi) = BLURRED_SPLITS[name]
    splits = cross_split(base)
    if not splits:
        return []
    sp = splits[0]
    folder = Path(tempfile.gettempdir()) / "favormap-bench-blur" / f"{name}-{lo:g}-{hi:g}-{seed}"
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    frames = []
    for f in sp.queries.frames:
        length, angle = rng.uniform(lo, hi), rng.uniform(0.0, np.pi)
        path = folder / (Path(f.name).stem + ".png")
        if not path.exists():
            img = cv2.imread(str(f.image_path), cv2.IMREAD_UNCHANGED)
            tmp = path.with_suffix(".part.png")
            cv2.imwrite(str(tmp), cv2.filter2D(img, -1, line_kernel(length, angle)))
            tmp.replace(path)
        frames.append(dataclasses.replace(f, image_path=path))
    queries = dataclasses.replace(sp.queries, frames=frames)
    out = dataclasses.replace(sp, name=name, queries=queries, map_name=base)
    return [out]


def line_kernel(length: float, angle: float) -> np.ndarray:
    """A normalised straight motion-blur kernel of ``length`` px at ``angle`` (radians), anti-aliased."""
    import cv2

    r = int(np.ceil(length / 2)) + 1
    k = np.zeros((2 * r + 1, 2 * r + 1), np.float32)
    d = np.array([np.cos(angle), np.sin(angle)]) * length / 2
    a, b = np.round(r - d).astype(int), np.round(r + d).astype(int)
    cv2.line(k, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), 1.0, 1, cv2.LINE_AA)
    return k / k.sum()


def with_pseudo_ground_truth(seq, path: Path):
    """``seq`` with the poses and focal of a pseudo ground truth file (one line per frame: image name,
    cam_from_world as quaternion w x y z and translation, focal in px), frames matched by their file stem.
    Refused when a frame has no pose there."""
    import dataclasses as dc

    from favormap.geometry import pose_from_quat_t

    def stem(name: str) -> str:
        return Path(name).name.split(".")[0]

    table = {}
    for line in path.read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            name, qw, qx, qy, qz, tx, ty, tz, focal = line.split()
            q, t = [float(qx), float(qy), float(qz), float(qw)], [float(tx), float(ty), float(tz)]
            table[stem(name)] = (pose_from_quat_t(q, t), float(focal))
    frames, focal = [], set()
    for fr in seq.frames:
        if stem(fr.name) not in table:
            raise SystemExit(f"{path}: no pose for frame {fr.name}")
        pose, f = table[stem(fr.name)]
        frames.append(dc.replace(fr, cam_from_world=pose))
        focal.add(f)
    if len(focal) != 1 or any(c.model != "PINHOLE" for c in seq.cameras.values()):
        raise SystemExit(f"{path}: expected one focal for pinhole cameras")
    f = focal.pop()
    cameras = {k: dc.replace(c, params=np.array([f, f, *c.params[2:]])) for k, c in seq.cameras.items()}
    return dc.replace(seq, cameras=cameras, frames=frames)


def nearest_view_angle(queries, mapping) -> np.ndarray:
    from favormap.geometry import pose_error

    return np.array(
        [min(pose_error(q.cam_from_world, m.cam_from_world)[1] for m in mapping.frames) for q in queries.frames]
    )


def orbit_split(workdir: Path, n_map: int, width: int, height: int, dense: bool = False) -> Split:
    """Mapping frames along part of the room orbit; queries (a) between mapping views, (b) orbiting
    on beyond the last mapping view, (c) raised above the path; binned by angle to the nearest view.

    ``dense`` ("orbit-dense", the same map): 53 queries instead of 25, at 4-degree steps orbiting
    7-59 degrees beyond both ends of the arc and raised 6-46 degrees above the path from four places
    along it (those whose camera leaves the room are dropped), 10 / 14 / 19 / 10 per angle bin. The
    standard set has 5 queries in the 10-20 degree bin, whose errors there lie at the pose's noise
    floor: a median over 5 of them moves more between two close methods than they differ."""
    from favormap.geometry import inverse, rotation_about
    from favormap.synthetic import camera_path, make_room, random_views_near, write_sequence

    scene = make_room(0)
    poses = camera_path(n_map)
    c = np.array([0.0, 0.55, 0.8])  # centre of the orbit (favormap.synthetic.paths._loop)

    def about(T, axis, deg):
        M = np.eye(4)
        M[:3, :3] = rotation_about(np.asarray(axis, float), np.radians(deg))
        M[:3, 3] = c - M[:3, :3] @ c
        return inverse(M @ inverse(T))

    q = list(random_views_near(poses, 4, seed=5, max_trans=0.03, max_rot_deg=3.0, scene=scene))
    last, first = poses[-1], poses[0]
    sign = 1.0 if np.cross(inverse(poses[-2])[:3, 3] - c, inverse(last)[:3, 3] - c)[2] > 0 else -1.0
    for deg in (6, 12, 18, 25, 32, 40, 45, 50, 55, 60, 70):
        q.append(about(last, [0, 0, 1], sign * deg))
    for base in (poses[len(poses) // 3], poses[2 * len(poses) // 3]):
        right = inverse(base)[:3, 0]  # camera x axis in world: tilting about it raises the camera over the scene
        for deg in (8, 15, 25, 35, 45):
            q.append(about(base, right, -deg))
    # before the first view too; the views beyond 40 deg (6 here) give that bin
    # of the angle table more than a couple of queries
    for deg in (10, 20, 45, 55):
        q.append(about(first, [0, 0, 1], -sign * deg))
    if dense:
        q = []
        for end, s in ((last, sign), (first, -sign)):
            q += [about(end, [0, 0, 1], s * deg) for deg in range(7, 61, 4)]
        for k in (1, 2, 3, 4):
            base = poses[k * len(poses) // 5]
            q += [about(base, inverse(base)[:3, 0], -deg) for deg in range(6, 47, 4)]
    q = [T for T in q if scene.camera_is_valid(inverse(T)[:3, 3])]
    mapping = write_sequence(workdir / "orbit_map", n_frames=n_map, width=width, height=height, scene=scene)
    name = "orbit-dense" if dense else "orbit"
    queries = write_sequence(
        workdir / f"{name.replace('-', '_')}_queries", poses=q, width=width, height=height, scene=scene
    )
    return Split(name, mapping, queries, nearest_view_angle(queries, mapping), map_name="orbit")
